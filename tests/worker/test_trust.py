"""The trust map and the height uncertainty (worker/trust.py) and their assets."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from worker.assets import derive_assets
from worker.trust import (
    AGREE,
    DISAGREE,
    FILLED,
    NORMALS_ONLY,
    REFINED,
    height_uncertainty_um,
    legend_scale_um,
    trust_classes,
)

S_UM = 50.0


def _maps(rows=40, cols=60, noise_um=2.0, seed=0):
    """A tablet mask with a border of 2 px off it, fringe disagreement of Gaussian noise,
    no fringe height in columns ≥ 40 and a 6 µm … 60 µm bias in a block."""
    rng = np.random.default_rng(seed)
    mask = np.zeros((rows, cols), bool)
    mask[2:-2, 2:-2] = True
    d = rng.normal(0.0, noise_um, (rows, cols))
    d[:, 40:] = np.nan
    d[10:14, 10:14] = 60.0  # fringes and normals pulled apart here
    d[~mask] = np.nan
    return mask, d


def test_classes_name_each_source():
    mask, d = _maps()
    guard = np.zeros(mask.shape, np.uint8)
    guard[20, 20] = 1
    walls = np.zeros(mask.shape, np.uint8)
    walls[25, 25] = 1
    c = trust_classes(mask, d, guard=guard, walls=walls)
    assert (c[~mask] == 0).all()
    assert (c[mask][:, None] > 0).all()
    assert (c[2:-2, 40:-2] == NORMALS_ONLY).all()
    assert (c[10:14, 10:14] == DISAGREE).all()
    assert c[20, 20] == FILLED and c[25, 25] == REFINED
    # Noise within 3σ agrees: nearly all of the fringe pixels outside the biased block.
    rest = c[2:-2, 2:40].copy()
    rest[8:12, 8:12] = AGREE
    assert (rest == AGREE).mean() > 0.98
    # No fringe heights at all: every tablet pixel rests on the normals.
    assert (trust_classes(mask, None)[mask] == NORMALS_ONLY).all()


def test_uncertainty_is_the_fringe_noise_where_anchored_and_grows_as_a_random_walk():
    mask, d = _maps(noise_um=2.0)
    d[10:14, 10:14] = np.nan  # (so the noise level is plain Gaussian)
    sig_t = 0.004
    sigma = height_uncertainty_um(mask, d, pixel_size_um=S_UM, normal_sigma=sig_t)
    assert np.isnan(sigma[~mask]).all() and np.isfinite(sigma[mask]).all()
    anchored = sigma[5:-5, 5:35]
    assert 1.5 < float(np.median(anchored)) < 2.6  # the local RMS of N(0, 2 µm)
    # Into the normals-only band: the anchor's σ and s·tan(σ_θ)·√n in quadrature.
    row = 20
    anchor = sigma[row, 39]
    for col in (45, 50, 57):
        n = col - 39
        expect = np.hypot(anchor, S_UM * np.tan(sig_t) * np.sqrt(n))
        assert sigma[row, col] == pytest.approx(expect, rel=0.15), col
    assert sigma[row, 57] > sigma[row, 45] > anchor


def test_guarded_pixels_are_not_anchors():
    mask, d = _maps()
    guard = np.zeros(mask.shape, np.uint8)
    guard[18:23, 18:23] = 1
    sig = height_uncertainty_um(mask, d, pixel_size_um=S_UM, guard=guard)
    plain = height_uncertainty_um(mask, d, pixel_size_um=S_UM)
    assert sig[20, 20] > plain[20, 20]


def test_without_fringes_heights_drift_from_the_middle():
    mask, _ = _maps()
    sig = height_uncertainty_um(mask, None, pixel_size_um=S_UM, normal_sigma=0.01)
    centre = np.unravel_index(np.nanargmin(sig), sig.shape)
    # The innermost pixels of a 36 × 56 rectangle are on its middle rows, ≥ 18 px from the rim.
    assert 19 <= centre[0] <= 20 and 19 <= centre[1] <= 40
    assert sig[2, 2] > sig[20, 20]


def test_bad_input_is_named():
    mask, d = _maps()
    with pytest.raises(ValueError, match="pixel_size_um"):
        height_uncertainty_um(mask, d, pixel_size_um=0)
    with pytest.raises(ValueError, match="must match"):
        trust_classes(mask, d[:-1])


def test_legend_scale_is_a_round_number_above_the_98th_percentile():
    mask = np.ones((10, 10), bool)
    v = np.linspace(0, 17.3, 100).reshape(10, 10)
    assert legend_scale_um(v, mask) == 20.0
    assert legend_scale_um(np.full((10, 10), 0.1), mask) == 1.0


def _model_dir(tmp_path, *, quality=True):
    from worker.durable import npy_bytes

    mask, d = _maps()
    h = np.where(mask, 100.0, np.nan).astype(np.float32)
    np.save(tmp_path / "height.npy", h)
    n = np.zeros((*h.shape, 3), np.float32)
    n[..., 2] = -1
    np.save(tmp_path / "normals.npy", n)
    (tmp_path / "report.json").write_text(
        json.dumps({"pixel_size_um": S_UM, "refinements": {"guard": {"pixels": 1}}})
    )
    if quality:
        (tmp_path / "quality").mkdir()
        (tmp_path / "quality" / "fringe_disagreement_um.npy").write_bytes(
            npy_bytes(d.astype(np.float32))
        )
        # A map of another grid is ignored, not misplaced.
        np.save(tmp_path / "quality" / "guard.npy", np.ones((3, 3), np.uint8))
    return mask


def test_derive_assets_writes_the_trust_map(tmp_path):
    mask = _model_dir(tmp_path)
    written = derive_assets(tmp_path)
    assert {"trust.png", "trust.json", "uncertainty_um.npy"} <= set(written)
    rgba = cv2.imread(str(tmp_path / "trust.png"), cv2.IMREAD_UNCHANGED)[..., [2, 1, 0, 3]]
    assert rgba.shape == (*mask.shape, 4)
    assert (rgba[..., 3][mask] == 255).all() and (rgba[..., 3][~mask] == 0).all()
    assert (rgba[2:-2, 40:-2, 0] == NORMALS_ONLY).all()
    assert (rgba[10:14, 10:14, 0] == DISAGREE).all()
    meta = json.loads((tmp_path / "trust.json").read_text())
    assert meta["inputs"] == ["fringe_disagreement_um"]  # the misfit guard map was left out
    assert meta["refinements"] == {"guard": {"pixels": 1}}
    # The biased block reads 60 µm: G = 255·60/scale.
    assert rgba[11, 11, 1] == round(255 * min(1.0, 60.0 / meta["disagreement_scale_um"]))
    sigma = np.load(tmp_path / "uncertainty_um.npy")
    assert sigma.dtype == np.float32 and np.isnan(sigma[~mask]).all()
    b = np.rint(255 * np.clip(sigma / meta["uncertainty_scale_um"], 0, 1))
    assert np.abs(rgba[..., 2][mask] - b[mask]).max() <= 1


def test_derive_assets_without_quality_maps_says_normals_only(tmp_path):
    mask = _model_dir(tmp_path, quality=False)
    derive_assets(tmp_path)
    meta = json.loads((tmp_path / "trust.json").read_text())
    assert meta["inputs"] == []
    assert meta["class_fraction"][str(NORMALS_ONLY)] == pytest.approx(1.0)
    assert np.isfinite(np.load(tmp_path / "uncertainty_um.npy")[mask]).all()
