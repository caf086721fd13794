"""The band-wise Wiener correction of the fused heights toward the fringe heights."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from worker.recon.band_wiener import (
    BAND_SCALES_PX,
    band_noise_gain,
    band_wiener_correct,
    fringe_noise_colour,
)

SHAPE = (160, 200)


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def _surface():
    """Smooth bumps and a slope, µm."""
    r, c = np.mgrid[: SHAPE[0], : SHAPE[1]].astype(np.float64)
    h = 0.8 * c + 40 * np.sin(r / 13.0) * np.cos(c / 17.0)
    return h.astype(np.float32)


def test_band_noise_gain_is_that_of_the_filters():
    # The identity minus a wide blur keeps nearly all white noise; the bands together hold
    # no more than the identity's unit variance (the DoG bands are nearly orthogonal).
    assert band_noise_gain(0.0, 32.0) == pytest.approx(1.0, abs=0.01)
    gains = [
        band_noise_gain(BAND_SCALES_PX[i], BAND_SCALES_PX[i + 1] if i + 1 < 7 else None)
        for i in range(7)
    ]
    assert all(g > 0 for g in gains)
    assert sum(gains) < 1.05
    # A continuous Gaussian of σ keeps 1/(4πσ²) of the variance of white noise.
    assert band_noise_gain(4.0, None) == pytest.approx(1 / (4 * np.pi * 16), rel=0.05)


def test_noise_colour_is_one_for_white_noise_and_grows_for_red_noise():
    rng = np.random.default_rng(1)
    truth = _surface()
    mask = np.ones(SHAPE, bool)
    sigma = np.full((4, *SHAPE), 2.0, np.float32)
    white = truth + rng.normal(0, 2.0, (4, *SHAPE)).astype(np.float32)
    kappa = fringe_noise_colour(white, sigma, mask)
    np.testing.assert_allclose(kappa[:5], 1.0, atol=0.25)
    # Noise correlated over ~3 px with the same per-pixel σ: far more variance at coarse
    # scales than white noise of that σ would have.
    raw = ndimage.gaussian_filter(rng.normal(0, 1.0, (4, *SHAPE)), (0, 3, 3))
    red = truth + (2.0 * raw / raw.std()).astype(np.float32)
    kappa_red = fringe_noise_colour(red, sigma, mask)
    assert kappa_red[3] > 5 * kappa[3]
    assert kappa_red[0] < 0.5  # and less at the pixel scale
    # One azimuth (nothing to compare) or no mask: white assumed.
    np.testing.assert_array_equal(fringe_noise_colour(white[:1], sigma[:1], mask), 1.0)
    np.testing.assert_array_equal(fringe_noise_colour(white, sigma, ~mask), 1.0)
    with pytest.raises(ValueError, match="must agree"):
        fringe_noise_colour(white, sigma[:2], mask)


def _case(bias_um, seed=2):
    rng = np.random.default_rng(seed)
    truth = _surface()
    fringe = truth + rng.normal(0, 2.0, SHAPE).astype(np.float32)
    bias = ndimage.gaussian_filter(rng.normal(0, 1.0, SHAPE), 2.0)
    bias = (bias_um * bias / bias.std()).astype(np.float32)
    fused = truth + bias + rng.normal(0, 0.3, SHAPE).astype(np.float32)
    return truth, fringe, fused


def _correct(fused, fringe, mask=None, **kw):
    m = np.ones(SHAPE, bool) if mask is None else mask
    return band_wiener_correct(
        fused,
        fringe,
        m,
        noise_sigma_um=np.full(SHAPE, 2.0, np.float32),
        crease_sigma_um=np.zeros(SHAPE, np.float32),
        colour=np.ones(len(BAND_SCALES_PX)),
        **kw,
    )


def test_a_bias_of_the_normals_above_the_fringe_noise_is_taken_out():
    # The fused surface carries a bias correlated over a few pixels (the normals'), 3 µm
    # RMS, where white fringe noise of 2 µm averages down: the correction removes most of it.
    truth, fringe, fused = _case(3.0)
    out = _correct(fused, fringe)
    before, after = _rms(fused - truth), _rms(out.height_um - truth)
    assert after < 0.6 * before, (before, after)
    assert max(out.acting_share) > 0.5


def test_it_stands_down_where_the_fused_surface_agrees_with_the_fringes():
    # No bias: the fused surface is better than the fringes everywhere; the correction must
    # not add their noise (it moves the heights by a small fraction of it).
    truth, fringe, fused = _case(0.0)
    out = _correct(fused, fringe)
    assert _rms(out.height_um - fused) < 0.35
    assert _rms(out.height_um - truth) < 1.3 * _rms(fused - truth) + 0.1
    # Where a band holds a few independent samples per window (the coarse ones on this small
    # frame) its local energy is a noisy estimate and the gain fluctuates above 0; the
    # finer bands must stay near 0.
    assert max(out.mean_gain[:4]) < 0.15


def test_fringe_outliers_and_holes_do_not_move_the_surface():
    # A block of wrong fringe orders (+800 µm), NaN fringe heights and a pixel off the mask:
    # heights near the block move by less than the noise, the off-mask pixel not at all.
    truth, fringe, fused = _case(0.0)
    fringe = fringe.copy()
    fringe[60:70, 80:95] += 800
    fringe[20:30, 20:30] = np.nan
    mask = np.ones(SHAPE, bool)
    mask[5, 5] = False
    out = _correct(fused, fringe, mask)
    assert np.abs(out.height_um - fused)[55:75, 75:100].max() < 2.0
    assert out.height_um[5, 5] == fused[5, 5]
    assert np.isfinite(out.height_um).all()


def test_a_blur_of_the_fringes_is_not_read_as_the_normals_error():
    # Fringes blurred by 1.5 px round a narrow groove the fused surface has right; told the
    # blur, the correction leaves the groove's depth alone; not told, it fills it in.
    r, c = np.mgrid[: SHAPE[0], : SHAPE[1]].astype(np.float32)
    truth = -60 * np.clip(1 - np.abs(c - 100) / 3, 0, None)
    rng = np.random.default_rng(4)
    fringe = ndimage.gaussian_filter(truth, 1.5) + rng.normal(0, 1.0, SHAPE).astype(np.float32)
    fused = truth + rng.normal(0, 0.3, SHAPE).astype(np.float32)

    def depth(h):
        return float(np.mean(h[20:-20, 90] - h[20:-20, 100]))

    told = _correct(fused, fringe, blur_px=1.5).height_um
    blind = _correct(fused, fringe, blur_px=0.0).height_um
    assert abs(depth(told) - depth(truth)) < 0.5 * abs(depth(blind) - depth(truth))
    assert abs(depth(told) - depth(truth)) < 6.0


def test_bands_finer_than_the_fringes_resolution_stand_down():
    # Fringe errors the azimuths share at the pixel scale (pixel mixing, a common phase
    # error) look like white noise of the right size to κ; told the fringes resolve nothing
    # finer than 1.5 px, the bands below stand down (no gain, no share) and leave those
    # scales to the fused surface, while the coarser bands still take out its bias.
    truth, fringe, fused = _case(3.0)
    out = _correct(fused, fringe, resolution_px=1.5)
    fine = [i for i, s in enumerate(BAND_SCALES_PX) if s < 1.5]
    assert fine == [0, 1]
    assert all(out.mean_gain[i] == 0.0 and out.acting_share[i] == 0.0 for i in fine)
    assert max(out.acting_share) > 0.5
    # What the correction adds below 1 px (the finest band's share of it): far less than
    # without the cut, where the fringes' pixel noise passes in.
    full = _correct(fused, fringe)

    def finest(h):
        moved = h - fused
        return _rms(moved - ndimage.gaussian_filter(moved, 1.0))

    assert finest(out.height_um) < 0.5 * finest(full.height_um), (
        finest(out.height_um),
        finest(full.height_um),
    )
    assert _rms(out.height_um - truth) < 0.8 * _rms(fused - truth)
    with pytest.raises(ValueError, match="resolution_px"):
        _correct(fused, fringe, resolution_px=-1.0)


def test_bad_shapes_are_refused():
    truth, fringe, fused = _case(0.0)
    with pytest.raises(ValueError, match="one shape"):
        _correct(fused[:-1], fringe[:-1])
    with pytest.raises(ValueError, match="one value per band"):
        band_wiener_correct(
            fused,
            fringe,
            np.ones(SHAPE, bool),
            noise_sigma_um=np.full(SHAPE, 2.0, np.float32),
            crease_sigma_um=np.zeros(SHAPE, np.float32),
            colour=np.ones(3),
        )
