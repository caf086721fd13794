"""worker.measure.measure_bundle: the streamed, threaded stages give what they give one by one."""

import numpy as np

from worker.bundle import open_bundle
from worker.measure import measure_bundle
from worker.recon.color import linear_to_srgb8
from worker.simulate import simulate_scan


def test_colour_in_background_gives_the_same_measurements(tmp_path):
    # The background colour stage works on frames decoded before the bundle closes and on
    # the normals already there: nothing it computes may depend on when it runs.
    simulate_scan(tmp_path, seed=5, preset="quick", noise="default", size=(96, 80))
    with open_bundle(tmp_path / "bundle") as bundle:
        inline = measure_bundle(bundle, progress=lambda stage, fraction: None)
        background = measure_bundle(
            bundle, progress=lambda stage, fraction: None, color_in_background=True
        )
    assert background.finish() is background
    assert not background.pending
    assert inline.rgb_linear is not None
    for name in ("rgb_linear", "normals", "albedo", "fringe_height_um", "modulation"):
        np.testing.assert_array_equal(getattr(background, name), getattr(inline, name))
    # The background stage also encodes the texture (beside the fusion): the same bytes.
    assert inline.rgb_srgb8 is None
    np.testing.assert_array_equal(background.rgb_srgb8, linear_to_srgb8(inline.rgb_linear))
    assert background.used == inline.used
    assert background.warnings == inline.warnings
    assert set(background.timings) == set(inline.timings) >= {"fringe", "photometric", "color"}
    # The fringe stage keeps what the camera blur is measured on (first azimuth, each period).
    periods = inline.used["fringe_periods_um"]
    first = min(periods, key=float)
    assert len(inline.reference_modulation) == len(periods[first])
    assert all(0 < m < 1.5 for m in inline.reference_modulation.values())
