"""Small device interfaces the acquisition code talks to (after python-microscope).

A driver for real hardware and a simulator implement the same abstract class, so
the acquisition, the tests and the CI runs exercise one code path. Every failure
a driver reports is a :class:`DeviceError` whose message is meant for the
operator: what happened, in plain words, and what to do.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from rig_agent.patterns import Pattern, ProjectorGeometry


class DeviceError(RuntimeError):
    """A device failed; ``str(error)`` is a plain-language message for the operator."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its time limit."""


@dataclass(frozen=True)
class StagePosition:
    """Where the motion axes are: light azimuth (degrees) and tablet elevation (mm)."""

    azimuth_deg: float
    elevation_mm: float


class Stage(abc.ABC):
    """The light-source azimuth axis (rotary, degrees) and the tablet elevation stage (mm)."""

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the connection and bring the controller to a known state."""

    @abc.abstractmethod
    def home(self) -> None:
        """Run the homing cycle; afterwards positions are absolute."""

    @abc.abstractmethod
    def move_to(self, *, azimuth_deg: float, elevation_mm: float) -> StagePosition:
        """Move both axes (absolute) and return once the motion has finished."""

    @abc.abstractmethod
    def position(self) -> StagePosition:
        """The current machine position."""

    @abc.abstractmethod
    def needs_homing(self) -> bool:
        """True when the controller lost its position (alarm, reset, power cycle)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connection (idempotent)."""


class Camera(abc.ABC):
    """A monochrome camera delivering single frames of stored values (0 … 2**bit_depth − 1)."""

    width: int
    height: int
    bit_depth: int

    @abc.abstractmethod
    def set_exposure(self, exposure: float) -> None:
        """Set the relative exposure (1.0 = the configured base exposure time)."""

    @abc.abstractmethod
    def capture(self) -> np.ndarray:
        """One frame, shape (height, width), dtype uint8 or uint16."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the camera (idempotent)."""


class Projector(abc.ABC):
    """Shows one pattern at a time on the light source's projector (see rig_agent.patterns)."""

    geometry: ProjectorGeometry

    @abc.abstractmethod
    def show(self, pattern: Pattern, *, azimuth_deg: float) -> None:
        """Display ``pattern`` for a source at ``azimuth_deg`` (fringes vary along u)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the display (idempotent)."""


def capture_average(camera: Camera, *, count: int) -> np.ndarray:
    """Mean of ``count`` frames, rounded back to the camera's integer type.

    Averaging N frames divides the shot and read noise by √N; the result stays in the
    camera's encoding so it can be stored like a single frame.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count must be a positive integer, got {count!r}")
    first = camera.capture()
    if count == 1:
        return first
    total = first.astype(np.float64)
    for _ in range(count - 1):
        total += camera.capture()
    return np.rint(total / count).astype(first.dtype)
