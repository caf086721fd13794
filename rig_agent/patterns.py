"""Projector pattern images for the light kinds of SCAN_BUNDLE.md (pure numpy).

The projector's image grid is mapped onto the reference plane like the camera's:
projector pixel (row r, column c) lights the plane point q = (c·s, r·s) µm, with
s = ``pixel_size_um`` the projector pixel pitch on the plane (x along columns, y
along rows). A fringe pattern of period P (µm, on the plane) and phase δ along the
source's horizontal direction u = (sin φ, cos φ) has the relative intensity

    I(q) = (1 + m·cos(2π (u·q)/P + δ)) / 2          (SCAN_BUNDLE.md, "fringe")

which is sent to the display as levels round((2^bits − 1) · I^(1/γ)) so that a
display with gamma γ emits light proportional to I. Solid white, red, green and
blue frames light every pixel at full level in the named channels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

KINDS = ("dark", "white", "color", "fringe")
CHANNELS = {"red": 0, "green": 1, "blue": 2}


@dataclass(frozen=True)
class ProjectorGeometry:
    """Projector image size (pixels), pitch on the reference plane (µm), bit depth, gamma."""

    width: int
    height: int
    pixel_size_um: float
    bit_depth: int = 8
    gamma: float = 1.0

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not (isinstance(self.bit_depth, int) and 1 <= self.bit_depth <= 16):
            raise ValueError(f"bit_depth must be an integer in 1..16, got {self.bit_depth!r}")
        if not self.pixel_size_um > 0:
            raise ValueError(f"pixel_size_um must be > 0, got {self.pixel_size_um!r}")
        if not self.gamma > 0:
            raise ValueError(f"gamma must be > 0, got {self.gamma!r}")

    @property
    def full_level(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        return np.uint8 if self.bit_depth <= 8 else np.uint16

    def span_um(self, azimuth_deg: float) -> float:
        """Extent of the projected image along u = (sin φ, cos φ), in µm on the plane."""
        phi = math.radians(azimuth_deg)
        return self.pixel_size_um * (
            abs(math.sin(phi)) * self.width + abs(math.cos(phi)) * self.height
        )

    def period_um_for(self, periods_across: float, *, azimuth_deg: float) -> float:
        """The period (µm) that fits ``periods_across`` periods across the image along u."""
        if not periods_across > 0:
            raise ValueError(f"periods_across must be > 0, got {periods_across!r}")
        return self.span_um(azimuth_deg) / periods_across


@dataclass(frozen=True)
class Pattern:
    """What the projector shows: a light kind and its parameters (µm, degrees)."""

    kind: str
    channel: str | None = None
    period_um: float | None = None
    phase_deg: float | None = None
    modulation: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if self.kind == "color" and self.channel not in CHANNELS:
            raise ValueError(f"channel must be one of {tuple(CHANNELS)}, got {self.channel!r}")
        if self.kind == "fringe":
            if self.period_um is None or not self.period_um > 0:
                raise ValueError(f"period_um must be > 0, got {self.period_um!r}")
            if self.phase_deg is None or not math.isfinite(self.phase_deg):
                raise ValueError(f"phase_deg must be a finite number, got {self.phase_deg!r}")
            if not 0 < self.modulation <= 1:
                raise ValueError(f"modulation must be in (0, 1], got {self.modulation!r}")

    def describe(self) -> str:
        if self.kind == "color":
            return f"solid {self.channel}"
        if self.kind == "fringe":
            return f"fringe P={self.period_um:g} µm δ={self.phase_deg:g}°"
        return "black" if self.kind == "dark" else "solid white"


def fringe_intensity(
    geometry: ProjectorGeometry,
    *,
    azimuth_deg: float,
    period_um: float,
    phase_deg: float,
    modulation: float = 1.0,
) -> np.ndarray:
    """Relative intensity I = (1 + m·cos(2π(u·q)/P + δ))/2, shape (height, width) float64."""
    if not period_um > 0:
        raise ValueError(f"period_um must be > 0, got {period_um!r}")
    if not 0 < modulation <= 1:
        raise ValueError(f"modulation must be in (0, 1], got {modulation!r}")
    phi = math.radians(azimuth_deg)
    x_um = np.arange(geometry.width, dtype=np.float64) * geometry.pixel_size_um
    y_um = np.arange(geometry.height, dtype=np.float64) * geometry.pixel_size_um
    along_u_um = math.sin(phi) * x_um[np.newaxis, :] + math.cos(phi) * y_um[:, np.newaxis]
    angle = 2 * math.pi * along_u_um / period_um + math.radians(phase_deg)
    return (1.0 + modulation * np.cos(angle)) / 2.0


def to_levels(intensity: np.ndarray, geometry: ProjectorGeometry) -> np.ndarray:
    """Display levels for a relative intensity in [0, 1], pre-compensating the gamma."""
    if np.any(intensity < 0) or np.any(intensity > 1):
        raise ValueError("intensity must lie in [0, 1]")
    encoded = intensity ** (1.0 / geometry.gamma)
    return np.rint(encoded * geometry.full_level).astype(geometry.dtype)


def render_pattern(
    pattern: Pattern, geometry: ProjectorGeometry, *, azimuth_deg: float
) -> np.ndarray:
    """The RGB image for ``pattern``: shape (height, width, 3), uint8 or uint16 levels."""
    shape = (geometry.height, geometry.width, 3)
    image = np.zeros(shape, dtype=geometry.dtype)
    if pattern.kind == "white":
        image[...] = geometry.full_level
    elif pattern.kind == "color":
        image[..., CHANNELS[pattern.channel]] = geometry.full_level
    elif pattern.kind == "fringe":
        intensity = fringe_intensity(
            geometry,
            azimuth_deg=azimuth_deg,
            period_um=pattern.period_um,
            phase_deg=pattern.phase_deg,
            modulation=pattern.modulation,
        )
        image[...] = to_levels(intensity, geometry)[..., np.newaxis]
    return image
