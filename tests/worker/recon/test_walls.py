"""Cliff pixels: mixture fractions, side heights, deblurring and the area-mean heights.

Synthetic scenes are rendered here from the spec's pixel model (SCAN_BUNDLE.md, "What a
pixel measures"): each pixel averages 8×8 sub-samples of a·exp(2πi(u·x − h·tanθ)/P) on the
object and exp(2πi·u·x/P) on the reference target, so a pixel straddling the wall mixes
both sides exactly as a camera pixel integrates its footprint.
"""

from __future__ import annotations

import numpy as np
import pytest

from worker.recon.walls import (
    CliffSamples,
    cliff_band,
    cliff_samples,
    deblur_fractions,
    mixture_amplitudes,
    own_amplitude,
    refine_cliff_heights,
    side_heights,
    unmeasured_jumps,
)

S_UM = 26.8
TAN = 1.0  # polar angle 45°
PERIODS = np.array([51200.0, 12800.0, 3200.0, 1600.0, 800.0, 400.0, 214.0])
SUB = 8


def _scene(size=32, cliff_um=600.0, angle_deg=20.0, offset_px=0.3, slope=(0.2, -0.1)):
    """Heights on an 8×8 sub-grid: two planes with the same slope, split by a straight wall.

    The wall is the line (x − c)·cos α + (y − c)·sin α = offset (pixel units, c the image
    centre); the side with the larger left-hand value is ``cliff_um`` higher.
    """
    k = (np.arange(size * SUB) + 0.5) / SUB - 0.5
    h_sub, upper = _heights(k, size, cliff_um, angle_deg, offset_px, slope)
    centre, _ = _heights(np.arange(size, dtype=float), size, cliff_um, angle_deg, offset_px, slope)
    return h_sub, upper, centre.astype(np.float32)


def _heights(k, size, cliff_um, angle_deg, offset_px, slope):
    y, x = np.meshgrid(k, k, indexing="ij")
    c = (size - 1) / 2
    a = np.radians(angle_deg)
    upper = (x - c) * np.cos(a) + (y - c) * np.sin(a) > offset_px
    base = S_UM * (slope[0] * x + slope[1] * y)
    return base + np.where(upper, cliff_um, 0.0), upper


def _box(a, size):
    return a.reshape(size, SUB, size, SUB).mean(axis=(1, 3))


def _render(h_sub, upper, size, azimuths, brightness, noise=0.0, rng=None):
    """CliffSamples of each azimuth: the pixel means of the object and reference responses."""
    k = (np.arange(size * SUB) + 0.5) / SUB - 0.5
    y, x = np.meshgrid(k * S_UM, k * S_UM, indexing="ij")
    out = []
    for az, (b_hi, b_lo) in zip(azimuths, brightness, strict=True):
        ux, uy = np.sin(np.radians(az)), np.cos(np.radians(az))
        bright = np.where(upper, b_hi, b_lo)
        amp, ph = [], []
        for p in PERIODS:
            carrier = 2 * np.pi * (ux * x + uy * y) / p
            obj = _box(bright * np.exp(1j * (carrier - 2 * np.pi * h_sub * TAN / p)), size)
            ref = _box(np.exp(1j * carrier), size)
            z = obj / ref
            if noise:
                z = z + noise * (rng.normal(size=z.shape) + 1j * rng.normal(size=z.shape))
            amp.append(np.abs(z).ravel())
            ph.append(np.angle(z).ravel())
        out.append(
            CliffSamples(
                flat_index=np.arange(size * size),
                amplitude=np.array(amp, np.float32),
                phase_rad=np.array(ph, np.float32),
                period_um=PERIODS,
                tan_theta=TAN,
            )
        )
    return out


def _normals(size, slope):
    """The planes' normals everywhere (a vertical wall shows no area)."""
    # n ∝ (−∂h/∂x, −∂h/∂y, −1) (SCAN_BUNDLE.md), ∂h/∂x = slope (µm per µm).
    n = np.array([-slope[0], -slope[1], -1.0]) / np.linalg.norm([slope[0], slope[1], 1.0])
    return np.broadcast_to(n, (size, size, 3)).astype(np.float32)


def test_mixture_amplitudes_recovers_the_two_shares_within_noise():
    rng = np.random.default_rng(1)
    n = 2000
    h_hi = rng.uniform(300, 1400, n)
    h_lo = rng.uniform(-300, 100, n)
    a_hi = rng.uniform(0, 0.6, n)
    a_lo = rng.uniform(0, 0.6, n)
    inv_p = 1.0 / PERIODS[:, None]
    z = a_hi * np.exp(-2j * np.pi * TAN * h_hi * inv_p) + a_lo * np.exp(
        -2j * np.pi * TAN * h_lo * inv_p
    )
    sigma = 0.01  # per real and imaginary part of each Z
    z = z + sigma * (rng.normal(size=z.shape) + 1j * rng.normal(size=z.shape))
    e_hi, e_lo = mixture_amplitudes(z, PERIODS, TAN, h_hi, h_lo)
    # Least squares: Re(conj(e)·noise) has variance σ² per level, so cov(a) = σ²·M⁻¹ with
    # M = [[L, c], [c, L]]; 5 standard deviations per pixel (2000 pixels: no false alarm).
    levels = PERIODS.size
    c = np.cos(2 * np.pi * TAN * np.outer(1 / PERIODS, h_hi - h_lo)).sum(0)
    sd = sigma * np.sqrt(levels / (levels**2 - c**2))
    assert np.all(np.abs(e_hi - a_hi) <= 5 * sd)
    assert np.all(np.abs(e_lo - a_lo) <= 5 * sd)


def test_own_amplitude_of_a_pure_pixel():
    h = np.array([0.0, 250.0, -800.0])
    z = 0.4 * np.exp(-2j * np.pi * TAN * np.outer(1 / PERIODS, h))
    np.testing.assert_allclose(own_amplitude(z, PERIODS, TAN, h), 0.4, atol=1e-12)


def test_deblur_fractions_inverts_the_variance_matched_kernel():
    rng = np.random.default_rng(2)
    size, sigma = 24, 0.45
    f_true = np.zeros((size, size))
    f_true[:, 12:] = 1.0
    rows = np.repeat(np.arange(size), 3)
    cols = np.tile([11, 12, 13], size)
    f_true[rows, cols] = rng.uniform(0, 1, rows.size)
    a = sigma**2 / 2
    k1 = np.array([a, 1 - 2 * a, a])
    from scipy import ndimage

    g = ndimage.convolve(f_true, np.outer(k1, k1), mode="nearest")
    known = np.where(np.arange(size)[None, :] >= 12, 1.0, 0.0) * np.ones((size, size))
    f = deblur_fractions(g[rows, cols], rows, cols, known, blur_sigma_px=sigma, iterations=60)
    # Exact data: the damped Jacobi iteration converges geometrically (contraction ≤ 0.6
    # per step at σ = 0.45); 60 steps leave far less than 1e-6.
    np.testing.assert_allclose(f, f_true[rows, cols], atol=1e-6)
    # σ = 0: the measured shares are the fractions.
    np.testing.assert_allclose(
        deblur_fractions(g[rows, cols], rows, cols, known, blur_sigma_px=0.0),
        np.clip(g[rows, cols], 0, 1),
    )


def test_side_heights_of_two_planes():
    size, slope = 32, (0.2, -0.1)
    _, upper, h = _scene(size, slope=slope)
    normals = _normals(size, slope)
    band = cliff_band(h, np.ones(h.shape, bool), min_jump_um=70.0, pixel_size_um=S_UM)
    rows, cols = np.nonzero(band)
    hi, lo, ok = side_heights(
        h, normals, ~band, rows, cols, pixel_size_um=S_UM, min_gap_um=35.0, radius=5
    )
    assert ok.mean() > 0.9
    plane = S_UM * (slope[0] * cols + slope[1] * rows)
    # Planes with exact normals: the Taylor predictions are exact (float32 heights).
    np.testing.assert_allclose(hi[ok], plane[ok] + 600.0, atol=1e-3)
    np.testing.assert_allclose(lo[ok], plane[ok], atol=1e-3)


@pytest.mark.parametrize("angle_deg, offset_px", [(20.0, 0.3), (90.0, -0.25), (-40.0, 0.1)])
def test_refine_gives_the_area_mean_at_a_cliff(angle_deg, offset_px):
    rng = np.random.default_rng(3)
    size, slope, cliff = 32, (0.2, -0.1), 600.0
    h_sub, upper, h = _scene(size, cliff_um=cliff, angle_deg=angle_deg, offset_px=offset_px)
    # Four azimuths; in the second the lower side lies in the projector's shadow.
    brightness = [(0.5, 0.3), (0.45, 0.0), (0.3, 0.35), (0.4, 0.25)]
    sigma = 0.005
    samples = _render(h_sub, upper, size, [0, 90, 180, 270], brightness, sigma, rng)
    normals = _normals(size, slope)
    mask = np.ones((size, size), bool)
    out, frac, _, _ = refine_cliff_heights(
        h, h, normals, mask, samples, pixel_size_um=S_UM, blur_sigma_px=0.0, sample="area"
    )
    truth = _box(h_sub, size)
    f_true = _box(upper.astype(float), size)
    # Pixels whose window (5 px) lies inside the image.
    inner = np.zeros((size, size), bool)
    inner[6:-6, 6:-6] = True
    straddle = (f_true > 0) & (f_true < 1) & inner
    assert np.isfinite(frac[straddle]).all()
    # Noise: each azimuth and side gives a share with σ ≤ σ_Z·√((M⁻¹)₁₁)/a ≈ σ_Z/(a·√L·0.9)
    # (M nearly diagonal: the sides' phases differ over the fine periods); the weakest
    # lit side (a = 0.25) bounds the combined estimate. Model: the fringe carrier turns
    # by 2π·s/P over a pixel, so a side's share of the pixel is seen with a phase of up
    # to π·s/P_min (0.39 rad at P = 214 µm, 8 px); fitting it as real loses 1 − cos, at
    # most 0.08 of that level's share, on one of L levels: ≤ 0.08/L overall. 5σ + model.
    levels = PERIODS.size
    tol_f = 5 * sigma / (0.25 * np.sqrt(levels) * 0.9) + 0.08 / levels
    assert np.abs(frac[straddle] - f_true[straddle]).max() <= tol_f
    assert np.abs(out - truth)[straddle].max() <= tol_f * cliff
    # Pixels the wall does not touch keep (within the same tolerance) their height.
    away = ~straddle & inner & np.isfinite(frac)
    assert np.abs(out - truth)[away].max() <= tol_f * cliff
    # A point sample (SCAN_BUNDLE.md): the side holding the pixel's centre, which a straight
    # wall leaves on the side with the larger share; clear shares pick the true side.
    point, pfrac, up, low = refine_cliff_heights(
        h, h, normals, mask, samples, pixel_size_um=S_UM, blur_sigma_px=0.0, sample="point"
    )
    np.testing.assert_array_equal(pfrac[straddle], frac[straddle])
    expected = np.where(frac >= 0.5, up, low)
    np.testing.assert_array_equal(point[straddle], expected[straddle])
    clear = straddle & (np.abs(f_true - 0.5) > tol_f)
    side_true = np.where(f_true > 0.5, up, low)
    np.testing.assert_array_equal(point[clear], side_true[clear])


def test_refine_with_camera_blur():
    rng = np.random.default_rng(4)
    size, slope, cliff, blur = 32, (0.2, -0.1), 600.0, 0.45
    h_sub, upper, h = _scene(size, cliff_um=cliff, angle_deg=30.0, offset_px=0.2)
    brightness = [(0.5, 0.3), (0.45, 0.0), (0.3, 0.35), (0.4, 0.25)]
    samples = _render(h_sub, upper, size, [0, 90, 180, 270], brightness, 0.0, rng)
    a = blur**2 / 2
    k1 = np.array([a, 1 - 2 * a, a])
    from scipy import ndimage

    for smp in samples:  # blur each period's object response by the camera's PSF (3×3)
        z = smp.amplitude * np.exp(1j * smp.phase_rad.astype(float))
        for i in range(z.shape[0]):
            zi = z[i].reshape(size, size)
            zi = ndimage.convolve(zi.real, np.outer(k1, k1), mode="nearest") + 1j * (
                ndimage.convolve(zi.imag, np.outer(k1, k1), mode="nearest")
            )
            smp.amplitude[i] = np.abs(zi).ravel()
            smp.phase_rad[i] = np.angle(zi).ravel()
    normals = _normals(size, slope)
    mask = np.ones((size, size), bool)
    out, frac, _, _ = refine_cliff_heights(
        h, h, normals, mask, samples, pixel_size_um=S_UM, blur_sigma_px=blur, sample="area"
    )
    f_true = _box(upper.astype(float), size)
    inner = np.zeros((size, size), bool)
    inner[6:-6, 6:-6] = True
    straddle = (f_true > 0) & (f_true < 1) & inner
    # Noise-free: the model terms of the unblurred test plus the reference's own blur,
    # which the object/reference ratio does not cancel for the blurred mixture (the
    # carrier's MTF at P_min, 1 − exp(−2π²σ²/P²) = 0.06 at 8 px, on one of L levels).
    tol_f = 0.08 / PERIODS.size + 0.06 / PERIODS.size + 0.02
    assert np.abs(frac[straddle] - f_true[straddle]).max() <= tol_f
    # Without deblurring the shares would be off by up to σ²/2 ≈ 0.1 next to the wall.
    assert np.abs(_box(h_sub, size) - out)[straddle].max() <= tol_f * cliff


def test_no_change_without_cliffs():
    rng = np.random.default_rng(5)
    size = 32
    k = (np.arange(size * SUB) + 0.5) / SUB - 0.5
    y, x = np.meshgrid(k, k, indexing="ij")
    # Rolling ground with a wedge-like groove: steep (up to ~55°) but continuous.
    h_sub = 300 * np.sin(x / 6.0) + 500 * np.exp(-(((x - 15) / 2.5) ** 2))
    upper = np.zeros_like(h_sub, bool)
    samples = _render(h_sub, upper, size, [0, 90], [(0.4, 0.4), (0.3, 0.3)], 0.005, rng)
    h = _box(h_sub, size).astype(np.float32)
    gy, gx = np.gradient(h.astype(float), S_UM)
    n = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    out, frac, _, _ = refine_cliff_heights(
        h,
        h,
        n.astype(np.float32),
        np.ones((size, size), bool),
        samples,
        pixel_size_um=S_UM,
        blur_sigma_px=0.45,
    )
    assert np.array_equal(out, h)
    assert np.isnan(frac).all()


def test_cliff_samples_keep_pixels_near_jumps_only():
    size = 64
    h = np.zeros((size, size), np.float32)
    h[:, 40:] = 500.0  # a cliff at column 40
    h[5, 5] = np.nan  # an unmeasured pixel
    levels = 3
    phase = np.zeros((levels, size, size), np.float32)
    amp_o = [np.full((size, size), 2.0, np.float32)] * levels
    amp_r = [np.full((size, size), 4.0, np.float32)] * levels
    smp = cliff_samples(
        h,
        phase,
        amp_o,
        amp_r,
        period_um=PERIODS[:levels],
        polar_deg=45.0,
        pixel_size_um=S_UM,
        radius=3,
    )
    rows, cols = np.divmod(smp.flat_index, size)
    assert set(np.unique(cols[rows > 12])) == set(range(36, 44))
    # The unmeasured pixel and its 4-neighbours form the edge, dilated by 3.
    assert (np.abs(rows[cols < 20] - 5) <= 4).all() and (np.abs(cols[cols < 20] - 5) <= 4).all()
    np.testing.assert_allclose(smp.amplitude, 0.5)
    assert smp.tan_theta == pytest.approx(1.0)


def test_fused_pixels_pulled_across_a_cliff_are_put_back():
    rng = np.random.default_rng(6)
    size, slope, cliff = 32, (0.2, -0.1), 600.0
    h_sub, upper, h_point = _scene(size, cliff_um=cliff, angle_deg=90.0, offset_px=0.3)
    brightness = [(0.5, 0.3), (0.45, 0.0), (0.3, 0.35), (0.4, 0.25)]
    sigma = 0.005
    samples = _render(h_sub, upper, size, [0, 90, 180, 270], brightness, sigma, rng)
    truth = _box(h_sub, size)
    # The fusion dragged the two rows below the wall's pixels half-way up the cliff.
    fused = truth.astype(np.float32).copy()
    f_true = _box(upper.astype(float), size)
    wall_rows = np.flatnonzero(((f_true > 0) & (f_true < 1)).any(axis=1))
    dragged = np.zeros((size, size), bool)
    dragged[wall_rows.max() + 1 : wall_rows.max() + 3, 6:-6] = True
    fused[dragged] += np.float32(0.4 * cliff)
    out, _, _, _ = refine_cliff_heights(
        fused,
        h_point,
        _normals(size, slope),
        np.ones((size, size), bool),
        samples,
        pixel_size_um=S_UM,
        blur_sigma_px=0.0,
    )
    # Each comes back to its side: as a refined pixel (f within the noise bound of
    # test_refine_gives_the_area_mean_at_a_cliff) or as a pure one (its fringe height).
    tol_f = 5 * sigma / (0.25 * np.sqrt(PERIODS.size) * 0.9) + 0.08 / PERIODS.size
    assert np.abs(out - truth)[dragged].max() <= tol_f * cliff


def test_samples_with_one_period_change_nothing():
    rng = np.random.default_rng(7)
    size, slope = 32, (0.2, -0.1)
    h_sub, upper, h = _scene(size, angle_deg=20.0, offset_px=0.3)
    samples = _render(h_sub, upper, size, [0], [(0.5, 0.3)], 0.0, rng)
    one = CliffSamples(
        samples[0].flat_index,
        samples[0].amplitude[-1:],
        samples[0].phase_rad[-1:],
        PERIODS[-1:],
        TAN,
    )
    out, frac, _, _ = refine_cliff_heights(
        h,
        h,
        _normals(size, slope),
        np.ones((size, size), bool),
        [one],
        pixel_size_um=S_UM,
        blur_sigma_px=0.45,
    )
    assert np.array_equal(out, h)
    assert np.isnan(frac).all()


def test_check_refinement_stands_down_where_a_side_is_not_measured():
    # Two terraces 600 µm apart; a refinement puts the wall's column on either side (kept)
    # and one pixel 40 mm up (a side extrapolated through a grazing normal): that pixel and
    # its changed neighbours get their input back, the rest of the wall keeps its refinement.
    from worker.recon.walls import check_refinement

    size = 24
    fringe = np.zeros((size, size), np.float32)
    fringe[:, 12:] = 600.0
    before = fringe.copy()
    before[:, 11:13] = 300.0  # the fusion's smeared wall
    after = before.copy()
    after[:, 11] = 0.0
    after[:, 12] = 600.0
    after[5, 12] = 40_000.0
    mask = np.ones((size, size), bool)
    got = check_refinement(before, after, fringe, mask)
    assert got.height_um[5, 12] == 300.0
    assert np.all(got.height_um[4:7, 11:13] == 300.0)  # the spoilt region stood down
    assert got.stood_down == 1 and got.stood_down_pixels == 6
    keep = np.ones((size, size), bool)
    keep[4:7, 11:13] = False
    np.testing.assert_array_equal(got.height_um[keep], after[keep])
    assert got.acted.sum() == 2 * size - 6
    # Nothing changed: nothing to check.
    same = check_refinement(before, before, fringe, mask)
    assert same.regions == 0 and not same.acted.any()


def test_unmeasured_jumps_are_cliffs_with_two_sides_or_steep_ground():
    # A terrace 600 µm high (a chip's wall) and, apart from it, ground rising at 80° to
    # the border (a break face): next to both the heights jump beyond what ground of 60°
    # rises. Beside the wall the normals are flat (a vertical wall shows no area): a
    # cliff, its pixels' side unknown; along the face they are steep and explain the jump
    # (steep ground, kept). Pixels the caller's evidence decided, or with a valid fringe height,
    # are never returned.
    rows, cols = 40, 60
    y, x = np.mgrid[0:rows, 0:cols]
    h = np.where(x >= 20, 600.0, 0.0).astype(np.float32)
    ramp = x >= 40
    # (The foot at half a pixel before x = 40: the mean normal of the pair (39, 40), half
    # flat and half steep, predicts its rise.)
    h = np.where(ramp, 600.0 + (x - 39.5) * S_UM * np.tan(np.radians(80)), h)
    h = h.astype(np.float32)
    normals = np.zeros((rows, cols, 3), np.float32)
    normals[..., 2] = -1.0
    t = np.tan(np.radians(80))
    normals[ramp] = np.array([-t, 0.0, -1.0]) / np.hypot(t, 1.0)
    mask = np.ones((rows, cols), bool)
    none = np.zeros((rows, cols), bool)
    fringe = np.full((rows, cols), np.nan, np.float32)
    got = unmeasured_jumps(h, fringe, normals, mask, none, valid=none, pixel_size_um=S_UM)
    assert got.cliff[5:-5, 19:21].all()  # the pixels on either side of the wall
    assert not got.cliff[:, 30:].any() and not got.steep[:, :30].any()
    assert got.steep[5:-5, 45:55].all() and not got.steep[:, :38].any()
    assert not (got.cliff & got.steep).any()
    # Decided by the fringe response, or a valid fringe height: never returned.
    decided = none.copy()
    decided[:, 19] = True
    valid = none.copy()
    valid[:, 20] = True
    got = unmeasured_jumps(h, fringe, normals, mask, decided, valid=valid, pixel_size_um=S_UM)
    assert not got.cliff[:, 19:21].any()
    # Without a jump, nothing.
    flat = np.zeros((rows, cols), np.float32)
    got = unmeasured_jumps(flat, fringe, normals, mask, none, valid=none, pixel_size_um=S_UM)
    assert not got.cliff.any() and not got.steep.any()
