"""Projectors: render the pattern of a shot, hand it to a display, wait until it is shown.

:class:`PatternProjector` renders with :func:`rig_agent.patterns.render_pattern`; a
display backend (a fullscreen window on the projector's output,
:class:`rig_agent.devices.display.WindowProjector`, or a vendor light engine SDK)
overrides :meth:`PatternProjector.display`. :class:`HeadlessProjector` keeps the last
image and pattern (for the simulated rig and for tests).

``show`` returns only when the camera may be triggered: ``display`` returns once the
frame has been handed to the output (at a vertical blank where the backend can wait for
one), then ``show`` waits ``settle_s`` more from that moment, for the scan-out and the
projector's own processing (input lag; a DLP projector's colour-wheel cycle).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from rig_agent.devices.base import Projector
from rig_agent.patterns import Pattern, ProjectorGeometry, render_pattern


class PatternProjector(Projector):
    """Renders patterns for its geometry; subclasses put the image on the display.

    ``clock`` (seconds, monotonic) and ``sleep`` are injectable so that tests check the
    settle delay without real waiting.
    """

    def __init__(
        self,
        geometry: ProjectorGeometry,
        *,
        render_images: bool = True,
        settle_s: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not settle_s >= 0:
            raise ValueError(f"settle_s must be >= 0, got {settle_s!r}")
        self.geometry = geometry
        self.render_images = render_images
        self.settle_s = float(settle_s)
        self.clock, self.sleep = clock, sleep
        self.current: Pattern | None = None
        self.azimuth_deg: float | None = None
        self.image: np.ndarray | None = None
        self.shown_at: float | None = None  # clock() when the last image reached the output

    def show(self, pattern: Pattern, *, azimuth_deg: float) -> None:
        self.current, self.azimuth_deg = pattern, azimuth_deg
        if self.render_images:
            self.image = render_pattern(pattern, self.geometry, azimuth_deg=azimuth_deg)
            self.display(self.image)
            self.shown_at = self.clock()
            self.wait_until(self.shown_at + self.settle_s)

    def wait_until(self, deadline: float) -> None:
        """Sleep until ``clock() >= deadline`` (a sleep may wake early: loop)."""
        while (remaining := deadline - self.clock()) > 0:
            self.sleep(remaining)

    def display(self, image: np.ndarray) -> None:
        """Put ``image`` (H, W, 3) on the projector and return once it is handed to the
        output; the default does nothing."""

    def close(self) -> None:
        self.current = None


class HeadlessProjector(PatternProjector):
    """A projector without a display: remembers what it was told to show."""
