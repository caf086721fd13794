"""Default fusion (worker.recon.fusion): known surfaces, fringe and normal noise of known size."""

import numpy as np
import pytest

from worker.recon.fusion import fuse_default

S_UM = 20.0
SIGMA_F_UM = 2.0  # fringe height noise per pixel
SIGMA_N_RAD = 0.005  # normal noise (≈ 0.3°)


def _surface(rows=96, cols=128):
    """A bump with a V-groove (wedge-like crease) on a tilted plane; exact slopes."""
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64) * S_UM
    cx, cy = cols * S_UM / 2, rows * S_UM / 2
    h = 80 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 600.0**2)) + 0.05 * x
    gx = -(x - cx) / 600.0**2 * (h - 0.05 * x) + 0.05
    gy = -(y - cy) / 600.0**2 * (h - 0.05 * x)
    return h, gx, gy


def _normals(gx, gy):
    n = np.stack([-gx, -gy, -np.ones_like(gx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def _noisy(rng, h, gx, gy):
    n = _normals(
        gx + rng.normal(0, SIGMA_N_RAD, gx.shape), gy + rng.normal(0, SIGMA_N_RAD, gy.shape)
    )
    f = (h + rng.normal(0, SIGMA_F_UM, h.shape)).astype(np.float32)
    return n, f


def _mask(shape):
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]]
    return ((x - shape[1] / 2) / (0.46 * shape[1])) ** 2 + (
        (y - shape[0] / 2) / (0.44 * shape[0])
    ) ** 2 < 1


def _rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


def _fuse(normals, fringe_height_um, mask, **options):
    """fuse_default with this module's pixel size and noise levels."""
    return fuse_default(
        normals,
        fringe_height_um,
        pixel_size_um=S_UM,
        mask=mask,
        normal_sigma_rad=SIGMA_N_RAD,
        height_sigma_um=SIGMA_F_UM,
        **options,
    )


def test_fused_heights_beat_both_inputs():
    # Expected fused error: the data term averages fringe noise over the footprint where the
    # slopes are trusted, radius L = σ_f/(s·σ_n) = 2/(20·0.005) = 20 px, i.e. ~πL² ≈ 1,200
    # pixels: σ ≈ σ_f/√(πL²)·√ln(...) ≈ 0.1–0.2 µm. We require under σ_f/4 = 0.5 µm RMS (4×
    # better than fringes alone), and a better shape than integrating the normals alone.
    rng = np.random.default_rng(11)
    h, gx, gy = _surface()
    n, f = _noisy(rng, h, gx, gy)
    mask = _mask(h.shape)
    got = _fuse(n, f, mask)
    assert np.all(np.isnan(got[~mask]))
    err = got[mask] - h[mask]
    assert abs(float(np.median(err))) < 0.2  # absolute heights come from the fringes
    assert _rms(err) < SIGMA_F_UM / 4
    assert _rms(err) < _rms(f[mask] - h[mask]) / 4
    # Threads (DCTs, the last solve's targets beside the first) change nothing.
    threaded = _fuse(n, f, mask, workers=2)
    np.testing.assert_array_equal(threaded, got)


def test_fringe_outliers_are_rejected():
    # 1 % of fringe heights off by 60 µm (unwrapping errors) must not dent the surface: after
    # the Cauchy re-weighting their weight is < (4σ_f/60)² ≈ 2 %, leaving dents under 0.5 µm.
    rng = np.random.default_rng(5)
    h, gx, gy = _surface()
    n, f = _noisy(rng, h, gx, gy)
    bad = rng.random(f.shape) < 0.01
    f = np.where(bad, f + 60, f).astype(np.float32)
    mask = _mask(h.shape)
    got = _fuse(n, f, mask)
    err = got[mask] - h[mask]
    assert _rms(err - np.median(err)) < SIGMA_F_UM / 4
    assert np.max(np.abs(err)) < 2.0


def test_region_without_fringes_is_reached_by_slopes():
    # A 30×30 px hole in the fringe heights (shadowed for every azimuth): heights there come
    # from the slopes, anchored at the hole's border; a random walk of ≤ 15 steps of s·σ_n =
    # 0.1 µm plus the border error stays well under 1 µm.
    rng = np.random.default_rng(8)
    h, gx, gy = _surface()
    n, f = _noisy(rng, h, gx, gy)
    f[33:63, 49:79] = np.nan
    mask = _mask(h.shape)
    got = _fuse(n, f, mask)
    err = (got - h)[33:63, 49:79]
    assert np.all(np.isfinite(err))
    assert np.max(np.abs(err)) < 1.0


def test_no_fringes_at_all_gives_the_integrated_normals_with_zero_mean():
    h, gx, gy = _surface()
    mask = _mask(h.shape)
    f = np.full(h.shape, np.nan, np.float32)
    got = _fuse(_normals(gx, gy), f, mask)
    assert abs(float(np.mean(got[mask]))) < 0.05
    err = got[mask] - h[mask]
    assert np.ptp(err) < 0.2  # shape exact up to the solver's tolerance (1e-3 of ~100 µm)


def test_inputs_are_not_modified_and_bad_sigma_is_named():
    rng = np.random.default_rng(1)
    h, gx, gy = _surface(32, 40)
    n, f = _noisy(rng, h, gx, gy)
    n0, f0 = n.copy(), f.copy()
    fuse_default(
        n,
        f,
        pixel_size_um=S_UM,
        mask=np.ones(f.shape, bool),
        normal_sigma_rad=0.01,
        height_sigma_um=1.0,
    )
    np.testing.assert_array_equal(n, n0)
    np.testing.assert_array_equal(f, f0)
    with pytest.raises(ValueError, match="height_sigma_um"):
        fuse_default(
            n,
            f,
            pixel_size_um=S_UM,
            mask=np.ones(f.shape, bool),
            normal_sigma_rad=0.01,
            height_sigma_um=0.0,
        )
    with pytest.raises(ValueError, match="fringe_height_um"):
        fuse_default(
            n,
            f[:, 1:],
            pixel_size_um=S_UM,
            mask=np.ones(f.shape, bool),
            normal_sigma_rad=0.01,
            height_sigma_um=1.0,
        )


def test_fringe_noise_is_estimated_on_a_curved_surface():
    # 60,000 second differences: the MAD's relative standard error is ~1.1/√N ≈ 0.5 %, so
    # 5 % covers it with the curvature's small contribution (2·0.001 µm per px²).
    from worker.recon.quality import fringe_sigma_um

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:200, 0:300]
    h = 0.3 * x + 0.001 * (x - 150) ** 2 + rng.normal(0, 1.5, x.shape)
    per_pixel, sigma = fringe_sigma_um(h, np.ones(h.shape, bool))
    assert sigma == pytest.approx(1.5, rel=0.05)
    assert np.allclose(per_pixel, sigma)


def test_normal_noise_follows_residual_and_light_count():
    # σ_θ² = σ_s²·2/(K sin²θ) + floor², σ_s = residual·√(K/(K−3)): K = 8, θ = 45°, residual
    # 0.02 → σ_s = 0.0253, σ_θ = √(0.0253²·0.5 + 0.003²) = 0.0183 rad.
    from worker.recon.quality import normal_sigma_rad

    res = np.array([[0.02, 0.0, np.nan]], np.float32)
    k = np.array([[8, 3, 0]], np.int16)
    sig = normal_sigma_rad(res, k, polar_deg=45.0)
    assert sig[0, 0] == pytest.approx(0.0183, rel=0.01)
    assert np.isfinite(sig[0, 1])  # 3 lights: the image's typical noise
    assert np.isinf(sig[0, 2])


def test_crease_error_is_zero_on_planes_and_large_at_a_v_groove():
    # Plane: zero Laplacian. V-groove with slopes ±0.5 (Δg = 1): the central difference gives
    # ∇²h = 1/(2s) at the two pixels beside the crease, so s²|∇²h|/8 = s/16 = 1.25 µm at s = 20.
    from worker.recon.quality import crease_sigma_um

    gx = np.where(np.arange(20) < 10, -0.5, 0.5)[None, :].repeat(8, 0)
    got = crease_sigma_um(_normals(gx, np.zeros_like(gx)), pixel_size_um=S_UM)
    np.testing.assert_allclose(got[:, [0, 5, 15, 19]], 0, atol=1e-5)
    np.testing.assert_allclose(got[:, [9, 10]], S_UM / 16, rtol=1e-4)
    plane = crease_sigma_um(
        _normals(np.full((5, 6), 0.3), np.full((5, 6), -0.2)), pixel_size_um=S_UM
    )
    np.testing.assert_allclose(plane, 0, atol=1e-5)


def _groove(rows=40, cols=80):
    """Pixel-averaged heights of a V-groove 300 µm wide and 60 µm deep along the columns."""
    ss = 16
    x = (np.arange(cols * ss) + 0.5) / ss * S_UM
    h = -np.clip(60 - np.abs(x - cols * S_UM / 2) * 60 / 150, 0, None)
    return np.tile(h.reshape(cols, ss).mean(axis=1), (rows, 1))


def test_sharpening_restores_a_blurred_groove_and_leaves_noise_alone():
    # A Gaussian blur of 0.6 px takes ~1.4 µm off the groove's depth at 20 µm pixels; the
    # second-order correction must bring back at least 2/3 of it (the O(σ⁴) rest). On a flat
    # noisy plane (no bend above 3σ of the Laplacian) the garrote keeps the heights within
    # 10 % of their noise.
    from scipy import ndimage

    from worker.recon.fusion import sharpen_heights

    h = _groove()
    blurred = ndimage.gaussian_filter1d(h, 0.6, axis=1, mode="nearest")
    mask = np.ones(h.shape, bool)
    c = h.shape[1] // 2
    lost = blurred[:, c].mean() - h[:, c].mean()
    assert lost > 1
    got = sharpen_heights(blurred, mask, blur_sigma_px=0.6, pixel_size_um=S_UM)
    assert abs(got[5:-5, c].mean() - h[5:-5, c].mean()) < lost / 3
    np.testing.assert_allclose(
        sharpen_heights(blurred, mask, blur_sigma_px=0.0, pixel_size_um=S_UM), blurred, atol=1e-4
    )
    rng = np.random.default_rng(3)
    flat = rng.normal(0, 1.0, (60, 60)).astype(np.float32)
    kept = sharpen_heights(flat, np.ones(flat.shape, bool), blur_sigma_px=0.6, pixel_size_um=S_UM)
    assert _rms(kept - flat) < 0.1


def test_sharpening_stands_down_at_a_lone_outlier():
    # A blurred groove with a one-pixel outlier beside it (what a single wrong normal leaves
    # in the fused heights): the groove is sharpened as without it, the outlier's own bend,
    # which none of its neighbours shares, is left as measured instead of being doubled.
    from scipy import ndimage

    from worker.recon.fusion import sharpen_heights

    clean = ndimage.gaussian_filter1d(_groove(), 0.6, axis=1, mode="nearest").astype(np.float32)
    spiked = clean.copy()
    r, c_out = 20, 10
    spiked[r, c_out] += 40.0
    mask = np.ones(clean.shape, bool)
    got_clean = sharpen_heights(clean, mask, blur_sigma_px=0.6, pixel_size_um=S_UM)
    got = sharpen_heights(spiked, mask, blur_sigma_px=0.6, pixel_size_um=S_UM)
    assert got[r, c_out] == spiked[r, c_out]  # not pushed further out
    c = clean.shape[1] // 2
    np.testing.assert_array_equal(got[:, c - 3 : c + 4], got_clean[:, c - 3 : c + 4])
    assert np.all(got[1:-1, c] < clean[1:-1, c] - 0.5)  # the floor still deepened (inner rows)


def test_point_sample_sharpening_undoes_the_pixel_area():
    # The pixel-averaged groove is shallower than its point samples at the pixel centres
    # (the V's tip is averaged over the pixel, 2 µm here); sharpening by the pixel's own area alone
    # (no camera PSF: σ² = 1/12 px²) brings the tip back toward the point sample, and a
    # camera PSF adds its variance.
    from worker.recon.fusion import PIXEL_AREA_VAR_PX2, point_sample_sigma_px, sharpen_heights

    cols, ss, c = 80, 16, 40
    tip = (c + 0.5) * S_UM  # the V's tip at a pixel's centre

    def v(x):
        return -np.clip(60 - np.abs(x - tip) * 60 / 150, 0, None)

    fine = v((np.arange(cols * ss) + 0.5) / ss * S_UM).reshape(cols, ss).mean(axis=1)
    area = np.tile(fine, (40, 1)).astype(np.float32)
    point = np.tile(v((np.arange(cols) + 0.5) * S_UM), (40, 1))
    lost = area[5:-5, c].mean() - point[5:-5, c].mean()
    assert lost > 1
    sigma = point_sample_sigma_px(0.0)
    assert sigma == pytest.approx(np.sqrt(PIXEL_AREA_VAR_PX2))
    got = sharpen_heights(area, np.ones(area.shape, bool), blur_sigma_px=sigma, pixel_size_um=S_UM)
    # A kink is where the second-order expansion is weakest: a quarter of the loss comes back.
    assert abs(got[5:-5, c].mean() - point[5:-5, c].mean()) < 0.8 * lost
    np.testing.assert_allclose(got[:, c + 3 : c + 6], area[:, c + 3 : c + 6])  # straight flank
    assert point_sample_sigma_px(0.5) == pytest.approx(np.sqrt(0.25 + 1 / 12))
    with pytest.raises(ValueError, match="camera_psf_px"):
        point_sample_sigma_px(-0.1)


def test_sharpening_depends_on_the_valid_pixels_only():
    # Heights on a ragged mask (holes, NaN, a border of invalid frame around it): the same
    # bits whatever the invalid frame around them (the correction works on their bounding
    # box), and the pixels off the mask are returned as they were.
    from worker.recon.fusion import sharpen_heights

    rng = np.random.default_rng(9)
    h = (_groove() + rng.normal(0, 0.3, _groove().shape)).astype(np.float32)
    mask = rng.random(h.shape) < 0.95
    h[rng.random(h.shape) < 0.02] = np.nan
    got = sharpen_heights(h, mask, blur_sigma_px=0.6, pixel_size_um=S_UM)
    framed_h = np.pad(h, ((3, 5), (7, 2)), constant_values=7.0)
    framed_m = np.pad(mask, ((3, 5), (7, 2)))
    framed = sharpen_heights(framed_h, framed_m, blur_sigma_px=0.6, pixel_size_um=S_UM)
    np.testing.assert_array_equal(framed[3:-5, 7:-2], got)
    np.testing.assert_array_equal(framed[~framed_m], framed_h[~framed_m])
    assert not np.array_equal(got[mask], h[mask])  # the groove's bends are corrected


def test_cell_average_targets_are_exact_for_a_cubic():
    # H(x) = pixel mean of h = a·x³: its slope at pixel centres is what a normal gives; the
    # four-point rule is exact for cubic H, the trapezoid rule errs by s³·H'''/12.
    from worker.recon.fusion import cell_average_targets_um
    from worker.recon.integrate import edge_targets_um

    a = 1e-6
    x = np.arange(30, dtype=np.float64) * S_UM
    big_h = a * x**3 + a * S_UM**2 * x / 4  # pixel mean of a·x³
    slope = 3 * a * x**2 + a * S_UM**2 / 4
    gx = np.tile(slope, (5, 1)).astype(np.float32)
    gy = np.zeros_like(gx)
    tx, ty = cell_average_targets_um(gx, gy, pixel_size_um=S_UM)
    want = np.diff(big_h)
    np.testing.assert_allclose(tx[:, 1:-1], np.tile(want[1:-1], (5, 1)), rtol=1e-4)
    trap, _ = edge_targets_um(gx, gy, pixel_size_um=S_UM)
    assert np.all(np.abs(trap[:, 1:-1] - want[1:-1]) > 0.5 * a * S_UM**3 / 2)
    np.testing.assert_allclose(ty, 0, atol=1e-6)


def test_a_cliff_that_the_normals_cannot_express_is_kept_from_the_fringes():
    # A 300 µm step along a column line (a chip's wall seen from above): the straddling pixels
    # carry a mixed-pixel normal that predicts a gentle 20 µm step, as stiff as any other
    # (σ_n per normal). Without the discontinuity test the stiff slopes would pull both sides
    # together over tens of pixels; with it, the step comes from the fringes, and pixels ≥ 3 px
    # from the wall keep the fringe-limited accuracy (σ_f/√(pixels averaged) ≪ 1 µm; 1 µm).
    rng = np.random.default_rng(21)
    h, gx, gy = _surface()
    wall = 64
    h = h + np.where(np.arange(h.shape[1]) >= wall, 300.0, 0.0)[None, :]
    gx = gx.copy()
    gx[:, wall - 1 : wall + 1] += 20.0 / S_UM / 2  # mixed pixels: a mild slope
    n, f = _noisy(rng, h, gx, gy)
    mask = _mask(h.shape)
    got = _fuse(n, f, mask)
    away = mask & (np.abs(np.arange(h.shape[1]) - wall + 0.5) > 3)[None, :]
    err = (got - h)[away]
    assert np.max(np.abs(err - np.median(err))) < 1.0


def _edge_problem(rng, sigma_e_um, sigma_f_um, rows=128, cols=128):
    """A smooth surface observed by independent edge steps and heights of known noise."""
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    h = 30 * np.sin(x / 17.0) * np.cos(y / 23.0) + 0.2 * x
    tx = (np.diff(h, axis=1) + rng.normal(0, 1, (rows, cols - 1)) * sigma_e_um).astype(np.float32)
    ty = (np.diff(h, axis=0) + rng.normal(0, 1, (rows - 1, cols)) * sigma_e_um).astype(np.float32)
    f = (h + rng.normal(0, 1, h.shape) * sigma_f_um).astype(np.float32)
    return h, tx, ty, f


@pytest.mark.parametrize(
    ("claimed_e", "true_e", "claimed_f", "true_f"),
    [(0.5, 1.5, 2.0, 2.0), (0.5, 0.5, 2.0, 6.0), (1.0, 1.0, 1.0, 1.0)],
)
def test_variance_factors_recover_the_true_noise(claimed_e, true_e, claimed_f, true_f):
    # The factors are (true σ / claimed σ)². The residuals of 16k heights and 32k edges give
    # each factor from a MAD, relative standard error ≈ 2·1.17/√n ≈ 1.8 % (heights) and 1.3 %
    # (edges); the lattice leverage is an approximation at the mask border (~3 % of the
    # pixels here) and where the weights vary: 10 % is over 5 standard errors.
    from worker.recon.fusion import variance_factors
    from worker.recon.integrate import solve_screened_poisson

    rng = np.random.default_rng(5)
    h, tx, ty, f = _edge_problem(rng, true_e, true_f)
    wx = np.full(tx.shape, 1 / claimed_e**2, np.float32)
    wy = np.full(ty.shape, 1 / claimed_e**2, np.float32)
    lam = np.full(f.shape, 1 / claimed_f**2, np.float32)
    # One round splits the misfit by the claimed weights' leverages; iterated (Förstner
    # 1979) the product of the rounds' factors converges to the truth.
    total_e, total_f = np.ones_like(wx), np.ones_like(lam)
    for _ in range(4):
        sol = solve_screened_poisson(tx, ty, wx, wy, data_um=f, data_weight=lam, rtol=1e-6)
        fx, fy, ff = variance_factors(sol.height_um, f, lam, wx, wy, tx, ty, classes=1)
        wx, wy, lam = wx / fx, wy / fy, lam / ff
        total_e, total_f = total_e * fx, total_f * ff
    assert np.allclose(total_e, (true_e / claimed_e) ** 2, rtol=0.1)
    assert np.allclose(total_f, (true_f / claimed_f) ** 2, rtol=0.1)


def test_variance_classes_separate_edges_whose_noise_was_ranked_wrongly():
    # Half the edges claim σ 0.5 but have 1.5, the other half claim 1.0 and have 1.0: with
    # two weight classes each gets its own factor (9 and 1); 16k edges per class give
    # ≈ 1.8 % relative standard error, the leverage's approximation a few %: 15 % tolerance.
    from worker.recon.fusion import variance_factors
    from worker.recon.integrate import solve_screened_poisson

    rng = np.random.default_rng(6)
    h, tx, ty, f = _edge_problem(rng, 1.0, 2.0)
    left_x = np.zeros(tx.shape, bool)
    left_x[:, : tx.shape[1] // 2] = True
    left_y = np.zeros(ty.shape, bool)
    left_y[:, : ty.shape[1] // 2] = True
    y, x = np.mgrid[0 : h.shape[0], 0 : h.shape[1]].astype(np.float64)
    h_true = 30 * np.sin(x / 17.0) * np.cos(y / 23.0) + 0.2 * x
    tx = np.where(left_x, np.diff(h_true, axis=1) + 1.5 * (tx - np.diff(h_true, axis=1)), tx)
    ty = np.where(left_y, np.diff(h_true, axis=0) + 1.5 * (ty - np.diff(h_true, axis=0)), ty)
    wx = np.where(left_x, 4.0, 1.0).astype(np.float32)
    wy = np.where(left_y, 4.0, 1.0).astype(np.float32)
    lam = np.full(f.shape, 0.25, np.float32)
    sol = solve_screened_poisson(
        tx.astype(np.float32), ty.astype(np.float32), wx, wy, data_um=f, data_weight=lam, rtol=1e-6
    )
    fx, fy, ff = variance_factors(sol.height_um, f, lam, wx, wy, tx, ty, classes=2)
    assert np.allclose(fx[left_x], 9.0, rtol=0.15)
    assert np.allclose(fx[~left_x], 1.0, rtol=0.15)
    assert np.allclose(fy[left_y], 9.0, rtol=0.15)
    # The leverages do not depend on the solution: computed beforehand, the same factors.
    from worker.recon.fusion import term_leverages

    given = variance_factors(
        sol.height_um, f, lam, wx, wy, tx, ty, classes=2, leverages=term_leverages(lam, wx, wy)
    )
    for a, b in zip(given, (fx, fy, ff), strict=True):
        np.testing.assert_array_equal(a, b)
    # The slope and height factors estimated in two threads: the same factors.
    threaded = variance_factors(sol.height_um, f, lam, wx, wy, tx, ty, classes=2, workers=2)
    for a, b in zip(threaded, (fx, fy, ff), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("size", [7, 100, 10_000])
def test_residual_sample_is_the_concatenation_strided(size):
    # Every step-th finite residual of the kept terms, group after group: the same values
    # as concatenating the groups' kept, finite terms and striding, for any phase.
    from worker.recon.fusion import _residual_sample

    rng = np.random.default_rng(8)
    groups = []
    for shape in ((13, 11), (12, 12), (5, 3)):
        w = rng.random(shape).astype(np.float32)
        u = rng.normal(size=shape).astype(np.float32)
        u[rng.random(shape) < 0.1] = np.nan
        groups.append((w, u, rng.random(shape) < 0.8))
    groups[1] = (groups[1][0].T, groups[1][1].T, groups[1][2].T)  # not C-contiguous
    weights = np.concatenate([w[keep] for w, _, keep in groups])
    u = np.concatenate([u[keep] for _, u, keep in groups])
    ok = np.isfinite(u)
    step = max(1, int(ok.sum()) // size)
    got_w, got_u = _residual_sample(*groups, size=size)
    np.testing.assert_array_equal(got_w, weights[ok][::step])
    np.testing.assert_array_equal(got_u, u[ok][::step])


def test_cauchy_weights_in_row_blocks_are_the_whole_frame_formula(monkeypatch):
    # Elementwise in blocks of rows (threads or not): bit for bit the whole-frame weights,
    # including the y-edges on the blocks' borders, NaN residuals (ρ = 1) and edges that may
    # not be cut.
    from worker.recon import fusion

    rng = np.random.default_rng(3)
    shape = (23, 17)
    h = rng.normal(0, 5, shape).astype(np.float32)
    f = (h + rng.normal(0, 1, shape)).astype(np.float32)
    f[rng.random(shape) < 0.1] = np.nan
    sig_f = rng.uniform(0.5, 2, shape).astype(np.float32)
    has_f = np.isfinite(f)
    lam = np.where(has_f, 1 / np.square(sig_f), 0).astype(np.float32)
    wx = rng.uniform(0, 3, (shape[0], shape[1] - 1)).astype(np.float32)
    wy = rng.uniform(0, 3, (shape[0] - 1, shape[1])).astype(np.float32)
    tx = rng.normal(0, 5, wx.shape).astype(np.float32)
    ty = rng.normal(0, 5, wy.shape).astype(np.float32)
    tx[0, 0] = np.nan
    cut_x, cut_y = rng.random(wx.shape) < 0.7, rng.random(wy.shape) < 0.7
    k = np.float32(4.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        zf = (h - f) / (k * sig_f)
        zx = (h[:, 1:] - h[:, :-1] - tx) * np.sqrt(wx) / k
        zy = (h[1:, :] - h[:-1, :] - ty) * np.sqrt(wy) / k
    rho_f = np.where(has_f, 1 / (1 + np.square(np.nan_to_num(zf))), 1)
    rho_x = np.where(cut_x, 1 / (1 + np.square(np.nan_to_num(zx))), 1)
    rho_y = np.where(cut_y, 1 / (1 + np.square(np.nan_to_num(zy))), 1)
    expected = (wx * rho_x, wy * rho_y, lam * rho_f)
    for block_px, workers in ((10_000, 1), (3 * shape[1], 1), (2 * shape[1], 2), (1, 2)):
        monkeypatch.setattr(fusion, "_ROBUST_BLOCK_PX", block_px)
        got = fusion._cauchy_weights(
            h, f, sig_f, has_f, lam, wx, wy, tx, ty, cut_x, cut_y, k=k, workers=workers
        )
        for a, b in zip(got, expected, strict=True):
            assert a.dtype == np.float32
            np.testing.assert_array_equal(a, b)


def test_variance_components_help_when_the_normals_are_worse_than_claimed():
    # Normals 4× noisier than their σ says: the estimated factor (≈ 16 in variance) gives
    # the fringe heights their due weight, so the fused heights must improve clearly (the
    # balance off by c = 16 costs (1 + c)²/4c ≈ 4.5× in variance, i.e. ~2× in RMS; we ask
    # for 10 %). With honest σ the slope factor comes out ≈ 0.6, not 1: two edges sharing a
    # pixel share its white noise, which the per-edge model does not know (on real normals,
    # whose errors are correlated over several pixels, the factor is ≈ 0.8). A balance off
    # by c = 2 costs at most (1 + c)²/4c = 9/8 in variance, ≈ 6 % in RMS: the bound used.
    rng = np.random.default_rng(12)
    h, gx, gy = _surface()
    mask = _mask(h.shape)
    n_bad = _normals(
        gx + rng.normal(0, 4 * SIGMA_N_RAD, gx.shape), gy + rng.normal(0, 4 * SIGMA_N_RAD, gy.shape)
    )
    n_ok, f = _noisy(rng, h, gx, gy)
    for normals, must_gain in ((n_bad, True), (n_ok, False)):
        errs = []
        for vce in (False, True):
            got = _fuse(normals, f, mask, variance_components=vce)
            e = (got - h)[mask]
            errs.append(_rms(e - e.mean()))
        if must_gain:
            assert errs[1] < 0.9 * errs[0], errs
        else:
            assert errs[1] < 1.061 * errs[0], errs


def test_pixels_straddling_a_cliff_do_not_carry_its_pull():
    # The same 300 µm wall, but the column of pixels straddling it has the area mean of both
    # sides (h + 150) and a fringe height that fits neither (the two sides' phases mix:
    # spread ±60 µm), so no edge next to it can be tested directly. Its two-edge paths are:
    # the wall is cut through it and it settles between the sides (within half the step of
    # its area mean), while pixels ≥ 2 px away keep the fringe-limited accuracy (1 µm, as
    # above).
    rng = np.random.default_rng(22)
    h, gx, gy = _surface()
    wall = 64
    cols = np.arange(h.shape[1])
    h = h + np.where(cols > wall, 300.0, np.where(cols == wall, 150.0, 0.0))[None, :]
    gx = gx.copy()
    gx[:, wall - 1 : wall + 2] += 20.0 / S_UM / 2
    n, f = _noisy(rng, h, gx, gy)
    f[:, wall] += rng.normal(0, 60.0, h.shape[0]).astype(np.float32)
    mask = _mask(h.shape)
    got = _fuse(n, f, mask)
    away = mask & (np.abs(cols - wall) >= 2)[None, :]
    err = (got - h)[away]
    assert np.max(np.abs(err - np.median(err))) < 1.0
    on = mask[:, wall]
    assert np.max(np.abs((got - h)[on, wall] - np.median(err))) < 150.0


def test_half_band_edge_slopes_keep_cubics_and_remove_the_nyquist_band():
    # [−1 4 10 4 −1]/16 across the edge: response 1 to fourth order at k = 0 (a cubic
    # passes exactly) and 0 at the Nyquist frequency (an alternating pattern, which is all
    # within the deviations' own spread and so not kept by the garrote, is removed).
    from worker.recon.fusion import transverse_mean_slopes

    rows, cols = 40, 30
    y = np.arange(rows, dtype=np.float64)[:, None] * np.ones((1, cols))
    cubic = 0.1 + 0.02 * (y - 20) - 1e-3 * (y - 20) ** 2 + 2e-5 * (y - 20) ** 3
    alternating = 0.01 * (-1.0) ** y
    gx = (cubic + alternating).astype(np.float32)
    gy = (cubic + alternating).T.astype(np.float32)  # the same, varying along columns
    ax, ay = transverse_mean_slopes(gx, gy)
    np.testing.assert_allclose(ax[2:-2], cubic[2:-2], atol=2e-6)
    np.testing.assert_allclose(ay[:, 2:-2], cubic.T[:, 2:-2], atol=2e-6)


def test_half_band_edge_slopes_halve_white_noise_and_keep_a_narrow_ridge():
    # White noise: the filter keeps Σk² = 134/256 = 0.523 of its variance (the garrote
    # keeps the few deviations beyond 3σ_d: +0.3 %); 160² samples fix the ratio to ~1 %.
    # A ridge one row wide and 20σ high along the x-edges deviates by 0.375·20σ from its
    # filtered value, far beyond 3σ_d = 3·0.523σ: the garrote keeps 1 − (1.57/7.5)² = 96 % of
    # it, so the row keeps > 95 % of its height (10/16 + 0.96·6/16 = 0.98).
    from worker.recon.fusion import transverse_mean_slopes

    rng = np.random.default_rng(5)
    g = rng.normal(0, 1, (160, 160)).astype(np.float32)
    ax, _ = transverse_mean_slopes(g, g)
    ratio = float(np.var(ax[3:-3]) / np.var(g[3:-3]))
    assert 0.50 < ratio < 0.56, ratio
    ridge = g.copy()
    ridge[80] += 20
    ax, _ = transverse_mean_slopes(ridge, ridge)
    assert float(np.mean(ax[80] - g[80] * 10 / 16)) > 0.95 * 20
    assert abs(float(np.mean(ax[79]))) < 0.1 * 20
    nan = g.copy()
    nan[10:20, 10:20] = np.nan
    ax, ay = transverse_mean_slopes(nan, nan)
    assert np.array_equal(np.isnan(ax), np.isnan(nan)) and np.isfinite(ax[9, 15])


@pytest.mark.parametrize("blur_px", [0.0, 1.0, 2.0])
def test_fringe_blur_is_measured_against_the_normals(blur_px):
    # Grooves 3–6 px wide (wedges) on a tilted plane; exact normals, fringe heights blurred by
    # a Gaussian of blur_px (light inside the clay) plus 0.5 µm noise, and a cliff the
    # median must ignore. The measured σ is the candidate nearest the truth.
    import cv2

    from worker.recon.quality import fringe_blur_px

    rng = np.random.default_rng(11)
    rows, cols = 120, 160
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    h = 0.3 * S_UM * x / 10
    for c0, w in ((20, 3), (50, 4), (80, 5), (115, 6)):
        h -= 40 * np.clip(1 - np.abs(x - c0 - 0.3 * y) / w, 0, None)
    h[:, 140:] += 500.0
    gy, gx = np.gradient(h, S_UM)
    n = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    f = h.astype(np.float32)
    if blur_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), blur_px, borderType=cv2.BORDER_REFLECT)
    f = f + rng.normal(0, 0.5, f.shape).astype(np.float32)
    mask = np.ones((rows, cols), bool)
    got = fringe_blur_px(f, n.astype(np.float32), mask, pixel_size_um=S_UM)
    assert abs(got - blur_px) <= 0.26, got
