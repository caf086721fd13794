"""The projector as a second monitor: a borderless fullscreen window showing each pattern.

On a scanner PC the projector is plugged into a display output and the desktop extends
onto it. :class:`WindowProjector` opens one SDL2 window (through pygame-ce) covering
display ``screen`` at its desktop resolution, without a mode change, borders or cursor,
and copies each pattern into it pixel for pixel: the window's size must be the
projector's native resolution, because ``projector_pixel_size_um`` is the pitch of
native pixels on the reference plane, and a scaled image would change the fringe
period and blur the levels. Levels pass through unchanged (SDL does no colour
management), so the gamma pre-compensation of :mod:`rig_agent.patterns` reaches the
projector as computed.

"On screen" is approached in two steps: the window presents through an SDL renderer
with vsync, so ``flip`` hands the frame over at a vertical blank (where the driver
honours it; :attr:`WindowProjector.vsync` says whether it does), then
:class:`~rig_agent.devices.projector.PatternProjector` waits the settle delay
(``projector_settle_ms``) before the camera may be triggered.

Tests and CI run it on SDL's ``dummy`` video driver (``SDL_VIDEODRIVER=dummy``: one
1024 × 768 display, no window system) and read the window's pixels back with
:meth:`WindowProjector.surface_pixels`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from rig_agent.devices.base import DeviceError
from rig_agent.devices.projector import PatternProjector
from rig_agent.patterns import ProjectorGeometry

# Hints SDL reads when the video subsystem starts (the environment wins if already set).
SDL_HINTS = {
    "PYGAME_HIDE_SUPPORT_PROMPT": "1",
    # the operator works on the other monitor: a fullscreen window must not minimise
    # when it loses the focus (SDL's default for fullscreen windows)
    "SDL_VIDEO_MINIMIZE_ON_FOCUS_LOSS": "0",
}


def _pygame() -> Any:
    for name, value in SDL_HINTS.items():
        os.environ.setdefault(name, value)
    try:
        import pygame
    except ImportError as exc:
        raise DeviceError(
            "the projector window needs pygame-ce: install the rig extra "
            '(pip install -e ".[rig]"), or set projector_display = "none"'
        ) from exc
    return pygame


def describe_displays(sizes: list[tuple[int, int]]) -> str:
    """``"2 displays: 0 (1920×1080), 1 (1280×800)"`` for an error message."""
    listed = ", ".join(f"{i} ({w}×{h})" for i, (w, h) in enumerate(sizes))
    return f"{len(sizes)} display{'s' if len(sizes) != 1 else ''}: {listed or 'none'}"


class WindowProjector(PatternProjector):
    """Patterns in a borderless fullscreen window on display ``screen`` (0 = the first).

    Opening fails with a :class:`DeviceError` naming the setting to change when the
    display does not exist, when its resolution is not the projector geometry's, or when
    the geometry asks for more than the 8 bits per channel a monitor output carries.
    Only one window per process (SDL's display module is process-wide).
    """

    _open = False

    def __init__(
        self,
        geometry: ProjectorGeometry,
        *,
        screen: int = 1,
        settle_s: float = 0.1,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> None:
        timing = {k: v for k, v in (("clock", clock), ("sleep", sleep)) if v is not None}
        super().__init__(geometry, settle_s=settle_s, **timing)
        if geometry.bit_depth != 8:
            raise DeviceError(
                f"projector_bit_depth {geometry.bit_depth}: a window on a display output "
                "shows 8 bits per channel; set projector_bit_depth = 8 (or drive the light "
                "engine through its own SDK)"
            )
        if isinstance(screen, bool) or not isinstance(screen, int) or screen < 0:
            raise DeviceError(f"projector_screen must be a display index >= 0, got {screen!r}")
        if WindowProjector._open:
            raise DeviceError("a projector window is already open in this process")
        self.screen = screen
        self.vsync = False
        self._surface = None
        self._owns_display = False
        self._pg = pg = _pygame()
        try:
            pg.display.init()
        except pg.error as exc:
            raise DeviceError(
                f"cannot open the display for the projector window ({exc}); run rig-agent in "
                'the scanner PC\'s desktop session, or set projector_display = "none"'
            ) from exc
        WindowProjector._open = self._owns_display = True
        try:
            self._surface = self._open_window()
        except BaseException:
            self.close()
            raise

    def _open_window(self) -> Any:
        pg, size = self._pg, (self.geometry.width, self.geometry.height)
        sizes = [tuple(s) for s in pg.display.get_desktop_sizes()]
        if not self.screen < len(sizes):
            raise DeviceError(
                f"projector_screen {self.screen} does not exist: this PC has "
                f"{describe_displays(sizes)}. Set projector_screen (or --projector-screen) "
                "to the projector's display"
            )
        if sizes[self.screen] != size:
            w, h = sizes[self.screen]
            raise DeviceError(
                f"display {self.screen} is {w}×{h} pixels but projector_width × "
                f"projector_height is {size[0]}×{size[1]}: set them to the projector's "
                "native resolution (desktop scaling 100 %), or choose another "
                f"projector_screen (this PC has {describe_displays(sizes)})"
            )
        with warnings.catch_warnings():
            # "no fast renderer available": SDL's software renderer, fine for a blit a shot
            warnings.simplefilter("ignore")
            try:
                # SCALED presents through an SDL renderer, which can wait for the vertical
                # blank; fullscreen at the desktop size is borderless, without a mode change,
                # and maps the window's pixels 1:1 onto the display's.
                surface = pg.display.set_mode(
                    size, pg.FULLSCREEN | pg.SCALED, display=self.screen, vsync=1
                )
            except pg.error:
                surface = pg.display.set_mode(size, pg.FULLSCREEN | pg.NOFRAME, display=self.screen)
        if surface.get_size() != size:
            raise DeviceError(
                f"the projector window on display {self.screen} came up "
                f"{surface.get_width()}×{surface.get_height()} instead of "
                f"{size[0]}×{size[1]}"
            )
        self.vsync = bool(pg.display.is_vsync())
        pg.display.set_caption("rig-agent projector")
        pg.mouse.set_visible(False)
        surface.fill((0, 0, 0))
        pg.display.flip()
        return surface

    def display(self, image: np.ndarray) -> None:
        pg = self._pg
        if self._surface is None:
            raise DeviceError("the projector window is closed")
        expected = (self.geometry.height, self.geometry.width, 3)
        if image.shape != expected or image.dtype != np.uint8:
            raise ValueError(f"image must be uint8 {expected}, got {image.dtype} {image.shape}")
        # Handling the window's events keeps it responsive to the window system.
        if any(event.type == pg.QUIT for event in pg.event.get()):
            raise DeviceError(
                "the projector window was closed; every frame so far is kept, "
                "`rig-agent resume` opens it again"
            )
        pg.surfarray.blit_array(self._surface, image.swapaxes(0, 1))
        pg.display.flip()

    def surface_pixels(self) -> np.ndarray:
        """What the window holds now: (height, width, 3) uint8, read back from its surface."""
        if self._surface is None:
            raise DeviceError("the projector window is closed")
        return self._pg.surfarray.array3d(self._surface).swapaxes(0, 1).copy()

    def close(self) -> None:
        super().close()
        self._surface = None
        if self._owns_display:
            self._pg.display.quit()
            WindowProjector._open = self._owns_display = False
