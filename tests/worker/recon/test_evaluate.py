"""worker.recon.evaluate: the accuracy figures of the benches, on known truth."""

from __future__ import annotations

import numpy as np

from worker.recon.evaluate import evaluate


def _scene():
    rows, cols = 40, 40
    r, c = np.mgrid[:rows, :cols]
    gt_h = np.zeros((rows, cols), np.float32)
    gt_h[18:23, 18:23] = -100.0  # a pit: the wedge
    gt_n = np.zeros((rows, cols, 3), np.float32)
    gt_n[..., 2] = -1.0
    gt_mask = (r >= 2) & (r < 38) & (c >= 2) & (c < 38)
    wedge = {
        "bottom": {"row": 20.0, "col": 20.0},
        "rim": [{"row": 20.0, "col": 12.0}, {"row": 20.0, "col": 28.0}],
    }
    return gt_h, gt_n, gt_mask, wedge


def test_figures_of_a_known_error():
    gt_h, gt_n, gt_mask, wedge = _scene()
    h = gt_h + 7.0  # an offset only: removed
    h[10, 10] += 60.0  # one spike
    h[0, 0] = -5000.0  # outside the true mask and its range
    mask = gt_mask.copy()
    mask[0, 0] = True
    f = evaluate(h, gt_n, mask, gt_height_um=gt_h, gt_normals=gt_n, gt_mask=gt_mask, wedges=[wedge])
    assert f["height_max_um"] == np.float32(60.0)
    # The spike (60 µm above a range whose top is 0) and the outlier outside the mask.
    assert f["height_spikes"] == 1 and f["height_out_of_range"] == 2
    assert f["mask_extra"] == 1 / gt_mask.sum()
    assert f["wedges"] == 1 and f["wedge_depth_mae_um"] < 1e-4
    assert f["normal_median_deg"] == 0.0 and f["normal_mean_deg"] == 0.0


def test_wedges_left_unreconstructed_are_not_counted():
    gt_h, gt_n, gt_mask, wedge = _scene()
    h = gt_h.copy()
    h[16:25, 16:25] = np.nan  # the chain left the wedge out
    f = evaluate(
        h, gt_n, gt_mask, gt_height_um=gt_h, gt_normals=gt_n, gt_mask=gt_mask, wedges=[wedge]
    )
    assert f["wedges"] == 0 and np.isnan(f["wedge_depth_mae_um"])


def test_wedges_with_a_rim_point_left_out_are_not_counted():
    # A rim point on a pixel the chain left NaN (a cliff pixel whose side is unknown) would
    # be read at the filled median height: the wedge is not counted.
    gt_h, gt_n, gt_mask, wedge = _scene()
    h = gt_h.copy()
    p = wedge["rim"][0]
    h[int(round(p["row"])), int(round(p["col"]))] = np.nan
    f = evaluate(
        h, gt_n, gt_mask, gt_height_um=gt_h, gt_normals=gt_n, gt_mask=gt_mask, wedges=[wedge]
    )
    assert f["wedges"] == 0 and np.isnan(f["wedge_depth_mae_um"])
