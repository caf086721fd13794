"""PatternProjector: ``show`` returns only after the frame was handed over plus the settle
delay (checked with an injected clock: no real waiting, no timing asserts)."""

from __future__ import annotations

import numpy as np
import pytest

from rig_agent.devices.projector import HeadlessProjector, PatternProjector
from rig_agent.patterns import Pattern, ProjectorGeometry

GEOMETRY = ProjectorGeometry(width=32, height=24, pixel_size_um=50.0)


class FakeClock:
    """Time that moves only when slept on; ``wake_early`` makes every other sleep end at a
    third of what was asked (a sleep interrupted by a signal: the projector must sleep
    again for the rest)."""

    def __init__(self, *, wake_early: bool = False) -> None:
        self.now, self.wake_early, self.sleeps = 1000.0, wake_early, []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        early = self.wake_early and len(self.sleeps) % 2
        self.now += seconds / 3 if early else seconds


class RecordingProjector(PatternProjector):
    """A display that takes one 60 Hz frame to hand the image over (a vsync'd flip)."""

    def __init__(self, clock: FakeClock, **kw) -> None:
        super().__init__(GEOMETRY, clock=clock, sleep=clock.sleep, **kw)
        self.fake, self.handed_over = clock, []

    def display(self, image: np.ndarray) -> None:
        self.fake.now += 1 / 60
        self.handed_over.append((self.fake.now, image.copy()))


@pytest.mark.parametrize("wake_early", [False, True])
def test_show_returns_after_the_frame_is_out_and_the_settle_delay(wake_early):
    clock = FakeClock(wake_early=wake_early)
    projector = RecordingProjector(clock, settle_s=0.1)
    for phase_deg in (0.0, 90.0):
        projector.show(Pattern("fringe", period_um=400.0, phase_deg=phase_deg), azimuth_deg=0.0)
        camera_trigger = clock()  # what acquire.capture does right after show()
        handed_over, image = projector.handed_over[-1]
        assert projector.shown_at == handed_over
        assert camera_trigger >= handed_over + 0.1
        assert np.array_equal(image, projector.image)
    # Exactly the delay is slept, in one piece or two (no busy loop, no extra wait).
    expected = [0.1, 0.2 / 3] * 2 if wake_early else [0.1, 0.1]
    assert clock.sleeps == pytest.approx(expected)


def test_no_delay_no_sleep_and_nothing_rendered_for_the_simulator():
    clock = FakeClock()
    projector = RecordingProjector(clock)
    projector.show(Pattern("white"), azimuth_deg=0.0)
    assert clock.sleeps == [] and len(projector.handed_over) == 1
    simulated = HeadlessProjector(GEOMETRY, render_images=False, settle_s=5.0, sleep=clock.sleep)
    simulated.show(Pattern("white"), azimuth_deg=0.0)
    assert simulated.image is None and simulated.current == Pattern("white")
    assert clock.sleeps == []


def test_negative_settle_is_refused():
    with pytest.raises(ValueError, match="settle_s"):
        HeadlessProjector(GEOMETRY, settle_s=-0.01)
