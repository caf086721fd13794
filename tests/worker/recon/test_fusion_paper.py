"""Kumar et al. 2003 fusion (worker.recon.fusion_paper)."""

import numpy as np
import pytest

from worker.recon.fusion_paper import (
    fried_block_heights,
    fried_block_matrix,
    fuse_paper,
    paper_lambda,
)

S_UM = 20.0


def test_fried_reconstructor_recovers_a_plane_with_zero_mean():
    g = fried_block_matrix()
    assert g.shape == (16, 18)
    r, c = np.mgrid[0:4, 0:4]
    plane = 0.3 * c - 0.7 * r
    slopes = np.concatenate([np.full(9, 0.3), np.full(9, -0.7)])
    np.testing.assert_allclose(g @ slopes, (plane - plane.mean()).ravel(), atol=1e-12)


def test_block_heights_are_lifted_to_their_means():
    gx = np.full((8, 12), 0.1, np.float32)
    gy = np.zeros((8, 12), np.float32)
    means = np.arange(6, dtype=np.float64).reshape(2, 3)
    h = fried_block_heights(gx, gy, pixel_size_um=S_UM, block_mean_um=means)
    np.testing.assert_allclose(h.reshape(2, 4, 3, 4).mean(axis=(1, 3)), means, atol=1e-5)
    np.testing.assert_allclose(np.diff(h[:, :4], axis=1), 0.1 * S_UM, atol=1e-5)
    with pytest.raises(ValueError, match="gx"):
        fried_block_heights(gx[:, :10], gy[:, :10], pixel_size_um=S_UM, block_mean_um=means)


def test_paper_fusion_improves_on_fringes_and_stops_by_the_rule():
    # σ_f = 2 µm fringe noise, 5×5 median ⇒ ≈ 1.25·2/5 = 0.5 µm (median efficiency 1/1.25);
    # the slope-driven update smooths further, so the fused RMS must be under that 0.5 µm bound.
    rng = np.random.default_rng(4)
    rows, cols = 64, 80
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64) * S_UM
    h = 1e-4 * (x - 800) ** 2 - 5e-5 * (y - 600) ** 2
    gx, gy = 2e-4 * (x - 800), -1e-4 * (y - 600)
    n = np.stack(
        [
            -gx - rng.normal(0, 0.005, gx.shape),
            -gy - rng.normal(0, 0.005, gx.shape),
            -np.ones_like(gx),
        ],
        -1,
    )
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    f = (h + rng.normal(0, 2.0, h.shape)).astype(np.float32)
    mask = np.ones(h.shape, bool)
    mask[:3] = False
    got, iterations = fuse_paper(
        n, f, pixel_size_um=S_UM, mask=mask, normal_sigma_rad=0.005, height_sigma_um=2.0
    )
    assert iterations >= 10
    assert np.all(np.isnan(got[:3]))
    inner = np.zeros_like(mask)
    inner[6:-3, 3:-3] = True
    err = (got - h)[inner]
    assert np.sqrt(np.mean(err**2)) < 0.5


def test_lambda_is_the_fringe_share():
    assert paper_lambda(
        normal_sigma_rad=0.01, height_sigma_um=0.2, pixel_size_um=20.0
    ) == pytest.approx(0.5)
