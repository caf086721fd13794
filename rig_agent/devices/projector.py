"""Projectors: render the pattern of a shot and hand it to a display.

:class:`PatternProjector` renders with :func:`rig_agent.patterns.render_pattern`; a
display backend (a fullscreen window on the projector's output, a vendor light
engine SDK) overrides :meth:`PatternProjector.display`. :class:`HeadlessProjector`
keeps the last image and pattern (for the simulated rig and for tests).
"""

from __future__ import annotations

import numpy as np

from rig_agent.devices.base import Projector
from rig_agent.patterns import Pattern, ProjectorGeometry, render_pattern


class PatternProjector(Projector):
    """Renders patterns for its geometry; subclasses put the image on the display."""

    def __init__(self, geometry: ProjectorGeometry, *, render_images: bool = True) -> None:
        self.geometry = geometry
        self.render_images = render_images
        self.current: Pattern | None = None
        self.azimuth_deg: float | None = None
        self.image: np.ndarray | None = None

    def show(self, pattern: Pattern, *, azimuth_deg: float) -> None:
        self.current, self.azimuth_deg = pattern, azimuth_deg
        if self.render_images:
            self.image = render_pattern(pattern, self.geometry, azimuth_deg=azimuth_deg)
            self.display(self.image)

    def display(self, image: np.ndarray) -> None:
        """Put ``image`` (H, W, 3) on the projector; the default does nothing."""

    def close(self) -> None:
        self.current = None


class HeadlessProjector(PatternProjector):
    """A projector without a display: remembers what it was told to show."""
