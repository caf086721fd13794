"""bench/fusion_ablation.py's pure helpers: the band split and the wedge error's sign."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

_BENCH = Path(__file__).resolve().parents[2] / "bench" / "fusion_ablation.py"


@pytest.fixture(scope="module")
def ablation():
    spec = importlib.util.spec_from_file_location("bench_fusion_ablation", _BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


def test_fine_and_coarse_bands_sum_to_the_error_and_split_by_scale(ablation):
    rows, cols = np.mgrid[0:96, 0:128].astype(np.float32)
    sel = np.ones((96, 128), bool)
    sel[:, :6] = False
    coarse_wave = 3 * np.sin(2 * np.pi * cols / 96)  # a 96 px period: above the split
    fine_wave = np.where((rows + cols) % 2 == 0, 1.0, -1.0).astype(np.float32)  # 1.4 px
    err = np.where(sel, coarse_wave + fine_wave, 0).astype(np.float32)
    fine, coarse = ablation.fine_coarse(err, sel)
    np.testing.assert_allclose((fine + coarse)[sel], err[sel], atol=1e-4)
    inner = sel.copy()
    inner[:, :40] = inner[:, -30:] = False
    inner[:30], inner[-30:] = False, False
    assert np.std(coarse[inner] - coarse_wave[inner]) < 0.3
    assert np.std(fine[inner] - fine_wave[inner]) < 0.3


def test_wedge_error_is_positive_for_a_wedge_too_deep(ablation):
    gt = np.zeros((20, 20), np.float32)
    gt[10, 10] = -100.0
    deeper = gt.copy()
    deeper[10, 10] = -110.0
    wedge = {
        "bottom": {"row": 10, "col": 10},
        "rim": [{"row": 10, "col": 5}, {"row": 5, "col": 10}],
    }
    core = np.ones((20, 20), bool)
    assert ablation.wedge_errors_um(deeper, gt, [wedge], core) == pytest.approx((10.0, 10.0))
    assert ablation.wedge_errors_um(gt, deeper, [wedge], core) == pytest.approx((10.0, -10.0))
    off_core = np.zeros((20, 20), bool)
    assert all(np.isnan(ablation.wedge_errors_um(deeper, gt, [wedge], off_core)))
