"""Gloss fit (worker.recon.gloss) on shading with a known Blinn–Phong lobe."""

import numpy as np
import pytest

from worker.recon.gloss import fit_gloss
from worker.recon.photometric import light_directions


def _dome(size=96):
    """Normals of a spherical cap (slopes up to ~50°) facing the camera, and its mask."""
    yy, xx = (np.mgrid[0:size, 0:size] - (size - 1) / 2) / (size / 2)
    r2 = xx**2 + yy**2
    mask = r2 < 0.95
    z = np.sqrt(np.clip(1.7 - r2, 1e-6, None))
    n = np.stack([xx, yy, -z], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[~mask] = np.nan
    return n, mask


def _shading(n, mask, lights, rho, ks, alpha, sigma, seed=0):
    v = np.array([0, 0, -1.0])
    half = lights + v
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    nn = np.where(mask[..., None], n, 0.0)
    ndl = np.maximum(np.einsum("hwc,kc->khw", nn, lights), 0)
    ndh = np.maximum(np.einsum("hwc,kc->khw", nn, half), 0)
    s = rho * ndl + ks * (ndh**alpha) * (ndl > 0)
    s += np.random.default_rng(seed).normal(0, sigma, s.shape)
    return np.where(mask, s, np.nan).astype(np.float32)


LIGHTS = light_directions(np.arange(8) * 45.0, 45.0)


@pytest.mark.parametrize("ks,alpha", [(0.2, 64.0), (0.1, 16.0)])
def test_recovers_the_lobe_of_a_glossy_dome(ks, alpha):
    n, mask = _dome()
    s = _shading(n, mask, LIGHTS, 0.5, ks, alpha, 0.005)
    res = fit_gloss(s, LIGHTS, n, mask, noise_sigma=0.005)
    assert res.exponent == alpha
    assert res.identified[mask].mean() > 0.3
    assert abs(np.median(res.strength[res.identified]) - ks) < 0.15 * ks
    # Filled pixels (the dome's top, where n·l and n·ĥ are the same under every light)
    # take their neighbours' strength, never zero and never a spike.
    filled = mask & ~res.identified
    assert filled.any()
    assert np.all(np.abs(res.strength[filled] - ks) < 0.3 * ks)


def test_a_matte_dome_stands_down():
    n, mask = _dome()
    s = _shading(n, mask, LIGHTS, 0.5, 0.0, 32.0, 0.005)
    res = fit_gloss(s, LIGHTS, n, mask, noise_sigma=0.005)
    assert res.exponent is None
    assert "stood_down" in res.report
    assert not res.strength.any()


def test_a_flat_surface_under_one_polar_angle_is_not_identifiable():
    size = 64
    n = np.zeros((size, size, 3))
    n[..., 2] = -1.0
    mask = np.ones((size, size), bool)
    s = _shading(n, mask, LIGHTS, 0.5, 0.3, 32.0, 0.002)
    res = fit_gloss(s, LIGHTS, n, mask, noise_sigma=0.002)
    assert res.exponent is None
    assert "not identifiable" in res.report["stood_down"]
    assert not res.identified.any()


def test_cast_shadows_and_missing_samples_do_not_make_gloss():
    n, mask = _dome()
    s = _shading(n, mask, LIGHTS, 0.5, 0.0, 32.0, 0.005)
    s[0, :, :30] = 0.0  # a cast shadow under one light
    s[3, 40:60, 40:60] = np.nan  # a reference too dark there
    res = fit_gloss(s, LIGHTS, n, mask, noise_sigma=0.005)
    assert res.exponent is None
