"""The projector window (SDL2 through pygame-ce) on SDL's dummy video driver: the pixels
that reach the window's surface are the levels of SCAN_BUNDLE.md's formula, the camera
waits for the flip plus the settle delay, and a wrong display is named clearly.

The dummy driver has one display, 1024 × 768, hence the geometry."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from rig_agent.devices.base import DeviceError
from rig_agent.devices.display import WindowProjector
from rig_agent.devices.factory import open_projector
from rig_agent.devices.projector import HeadlessProjector
from rig_agent.patterns import Pattern, ProjectorGeometry
from rig_agent.settings import Settings

GEOMETRY = ProjectorGeometry(width=1024, height=768, pixel_size_um=30.0, gamma=2.2)


@pytest.fixture(autouse=True)
def sdl_dummy(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")


@pytest.fixture
def window():
    projector = WindowProjector(GEOMETRY, screen=0, settle_s=0.0)
    yield projector
    projector.close()


def spec_levels(*, azimuth_deg, period_um, phase_deg, modulation, gamma=2.2):
    """SCAN_BUNDLE.md's fringe, written out again: I(q) = (1 + m·cos(2π(u·q)/P + δ))/2 at
    q = (c·s, r·s) µm, u = (sin φ, cos φ), sent as levels 255·I^(1/γ) (unrounded)."""
    rows, cols = np.mgrid[0 : GEOMETRY.height, 0 : GEOMETRY.width].astype(np.float64)
    phi = math.radians(azimuth_deg)
    u_dot_q = (math.sin(phi) * cols + math.cos(phi) * rows) * GEOMETRY.pixel_size_um
    intensity = (
        1 + modulation * np.cos(2 * math.pi * u_dot_q / period_um + math.radians(phase_deg))
    ) / 2
    return 255 * intensity ** (1 / gamma)


@pytest.mark.parametrize(
    ("azimuth_deg", "period_um", "phase_deg", "modulation"),
    [
        (0.0, 960.0, 0.0, 1.0),
        (90.0, 240.0, 90.0, 1.0),
        (225.0, 3070.0, 270.0, 0.8),
        (30.0, 61.5, 180.0, 1.0),
    ],
)
def test_fringes_on_the_window_follow_the_spec_formula(
    window, azimuth_deg, period_um, phase_deg, modulation
):
    pattern = Pattern("fringe", period_um=period_um, phase_deg=phase_deg, modulation=modulation)
    window.show(pattern, azimuth_deg=azimuth_deg)
    pixels = window.surface_pixels()
    assert pixels.shape == (768, 1024, 3) and pixels.dtype == np.uint8
    expected = spec_levels(
        azimuth_deg=azimuth_deg, period_um=period_um, phase_deg=phase_deg, modulation=modulation
    )
    # Integer levels: each pixel is the formula rounded, at most half a level off (plus
    # float noise where the formula lands on a half).
    for channel in range(3):
        assert np.abs(pixels[..., channel] - expected).max() <= 0.5 + 1e-9


def test_solid_colours_and_black_reach_the_window(window):
    for pattern, rgb in [
        (Pattern("white"), (255, 255, 255)),
        (Pattern("color", channel="red"), (255, 0, 0)),
        (Pattern("color", channel="green"), (0, 255, 0)),
        (Pattern("color", channel="blue"), (0, 0, 255)),
        (Pattern("dark"), (0, 0, 0)),
    ]:
        window.show(pattern, azimuth_deg=90.0)
        pixels = window.surface_pixels()
        assert np.all(pixels == np.array(rgb, dtype=np.uint8)), pattern.describe()


class FakeClock:
    """Monotonic time that moves only when slept on."""

    def __init__(self) -> None:
        self.now, self.sleeps = 50.0, []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def test_the_camera_waits_for_the_flip_and_the_settle_delay(monkeypatch):
    clock = FakeClock()
    projector = WindowProjector(GEOMETRY, screen=0, settle_s=0.25, clock=clock, sleep=clock.sleep)
    try:
        pg = projector._pg
        flips, real_flip = [], pg.display.flip

        def flip():
            real_flip()
            clock.now += 1 / 60  # a vsync'd present returns at the next vertical blank
            flips.append(clock.now)

        monkeypatch.setattr(pg.display, "flip", flip)
        projector.show(Pattern("fringe", period_um=500.0, phase_deg=90.0), azimuth_deg=45.0)
        camera_trigger = clock()
        assert len(flips) == 1
        assert projector.shown_at == flips[0]
        assert camera_trigger >= flips[0] + 0.25
        assert clock.sleeps == pytest.approx([0.25])
        assert np.array_equal(projector.surface_pixels(), projector.image)
    finally:
        projector.close()


def test_a_missing_display_is_named_with_the_ones_that_exist():
    with pytest.raises(DeviceError) as excinfo:
        WindowProjector(GEOMETRY, screen=1)
    message = str(excinfo.value)
    assert "projector_screen 1 does not exist" in message
    assert "1 display: 0 (1024×768)" in message
    # The failed attempt leaves nothing open: the next one works.
    WindowProjector(GEOMETRY, screen=0).close()


def test_a_display_of_another_resolution_is_refused():
    geometry = ProjectorGeometry(width=1280, height=800, pixel_size_um=30.0)
    with pytest.raises(DeviceError, match=r"display 0 is 1024×768 pixels but .* is 1280×800"):
        WindowProjector(geometry, screen=0)


def test_more_than_eight_bits_is_refused():
    geometry = ProjectorGeometry(width=1024, height=768, pixel_size_um=30.0, bit_depth=10)
    with pytest.raises(DeviceError, match="projector_bit_depth 10"):
        WindowProjector(geometry, screen=0)


def test_without_pygame_or_without_a_display(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "no-such-driver")
    with pytest.raises(DeviceError, match="cannot open the display"):
        WindowProjector(GEOMETRY, screen=0)
    monkeypatch.setitem(sys.modules, "pygame", None)
    with pytest.raises(DeviceError, match="pygame-ce"):
        WindowProjector(GEOMETRY, screen=0)


def test_one_window_at_a_time_and_closing(window):
    with pytest.raises(DeviceError, match="already open"):
        WindowProjector(GEOMETRY, screen=0)
    window.close()
    window.close()  # idempotent
    with pytest.raises(DeviceError, match="closed"):
        window.show(Pattern("white"), azimuth_deg=0.0)


def test_closing_the_window_stops_the_scan(window):
    pg = window._pg
    pg.event.post(pg.event.Event(pg.QUIT))
    with pytest.raises(DeviceError, match="projector window was closed.*rig-agent resume"):
        window.show(Pattern("white"), azimuth_deg=0.0)


def test_the_settings_choose_the_backend():
    headless = open_projector(Settings(projector_display="none"))
    assert isinstance(headless, HeadlessProjector)
    settings = Settings(
        projector_width=1024, projector_height=768, projector_screen=0, projector_settle_ms=40.0
    )
    projector = open_projector(settings)
    try:
        assert isinstance(projector, WindowProjector)
        assert projector.settle_s == pytest.approx(0.04)
        assert projector.geometry.gamma == settings.projector_gamma
    finally:
        projector.close()
