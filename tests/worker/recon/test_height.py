import numpy as np
import pytest

from worker.recon.height import (
    combine_azimuths,
    consensus_azimuths,
    fill_holes,
    height_from_phase,
)


def test_height_from_phase_follows_the_spec_sign():
    # A point raised toward the camera (h > 0) shifts the phase by Δψ = −2π h tanθ / P.
    h = np.array([[0.0, 10.0, -25.0]])
    dpsi = -2 * np.pi * h * np.tan(np.deg2rad(30.0)) / 400.0
    np.testing.assert_allclose(
        height_from_phase(dpsi, period_um=400.0, polar_deg=30.0), h, atol=1e-4
    )


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"period_um": 0.0, "polar_deg": 30.0}, "period_um"),
        ({"period_um": 1.0, "polar_deg": 90.0}, "polar_deg"),
    ],
)
def test_height_from_phase_rejects_bad_input(kwargs, culprit):
    with pytest.raises(ValueError, match=culprit):
        height_from_phase(np.zeros(3), **kwargs)


def test_combine_azimuths_rejects_corrupted_and_shadowed_azimuths():
    rng = np.random.default_rng(4)
    a, shape = 5, (40, 40)
    truth = rng.uniform(-300, 300, shape)
    sigma = 2.0
    heights = truth[None] + rng.normal(0.0, sigma, (a,) + shape)
    weight = np.ones((a,) + shape)
    # Azimuth 1 is corrupted (a wrong fringe order, +40 µm) on the left half.
    heights[1, :, :20] += 40.0
    # Azimuth 3 is shadowed on the top rows: garbage heights with weight 0.
    heights[3, :10] = 1e4
    weight[3, :10] = 0.0
    # Azimuth 4 has no data at all on one column.
    heights[4, :, 35] = np.nan
    res = combine_azimuths(heights, weight)
    # The mean of n inliers has σ/√n; with n ≥ 3 the error stays below 5.5·σ/√3 (1,600 pixels,
    # chance of exceeding ~1e-4 each... 5.5σ of the mean: negligible).
    n = res.azimuths_used
    assert np.all(np.abs(res.height_um - truth) <= 5.5 * sigma / np.sqrt(n))
    expected = np.full(shape, 5)
    expected[:, :20] -= 1
    expected[:10] -= 1
    expected[:, 35] -= 1
    # An honest inlier deviates from the median of n ≈ 4 with sd ≈ σ·sqrt(1 + π/(2n)) ≈ 1.2σ,
    # so it falls outside 3σ with p ≈ 1 %; with ~4 inliers ~4 % of pixels lose one: bound 10 %.
    assert np.mean(n == expected) > 0.9 and np.all(n <= expected)
    assert np.nanmedian(res.spread_um) < 2 * sigma


def test_combine_azimuths_nan_where_no_azimuth_sees():
    h = np.zeros((2, 3, 3))
    w = np.ones((2, 3, 3))
    w[:, 1, 1] = 0
    res = combine_azimuths(h, w)
    assert np.isnan(res.height_um[1, 1]) and res.azimuths_used[1, 1] == 0
    assert np.all(res.height_um[0] == 0)


@pytest.mark.parametrize(
    ("h", "w", "culprit"),
    [
        (np.zeros((3, 3)), np.zeros((3, 3)), "height_um"),
        (np.zeros((2, 3, 3)), np.zeros((2, 3, 4)), "weight"),
        (np.zeros((2, 3, 3)), -np.ones((2, 3, 3)), "weight"),
    ],
)
def test_combine_azimuths_rejects_bad_input(h, w, culprit):
    with pytest.raises(ValueError, match=culprit):
        combine_azimuths(h, w)


def test_fill_holes_reproduces_a_plane_and_leaves_the_rest():
    yy, xx = np.mgrid[0:30, 0:40].astype(float)
    plane = 3.0 * xx - 2.0 * yy + 7.0
    z = plane.copy()
    z[5:12, 8:20] = np.nan  # a hole inside the tablet
    z[20:25, 30:33] = np.nan
    z[:, 38:] = np.nan  # off the tablet: stays NaN
    mask = np.ones(z.shape, dtype=bool)
    mask[:, 38:] = False
    before = z.copy()
    out = fill_holes(z, mask)
    np.testing.assert_array_equal(np.isnan(before), np.isnan(z))  # input untouched
    # A plane is harmonic, so the discrete Laplace fill reproduces it exactly.
    np.testing.assert_allclose(out[:, :38], plane[:, :38], atol=1e-3)
    assert np.all(np.isnan(out[:, 38:]))


def test_fill_holes_without_any_rim_stays_nan():
    z = np.full((5, 5), np.nan)
    z[0, 0] = 1.0
    mask = np.zeros((5, 5), dtype=bool)
    mask[2:4, 2:4] = True  # an isolated hole with no finite neighbour
    out = fill_holes(z, mask)
    assert np.all(np.isnan(out[2:4, 2:4]))
    with pytest.raises(ValueError, match="mask"):
        fill_holes(z, mask.astype(int))


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 210.0])
def test_fringe_chain_follows_the_spec_geometry(azimuth_deg):
    from worker.recon.fringe import four_step_phase
    from worker.recon.unwrap import phase_difference

    # Straight from SCAN_BUNDLE.md: the ray reaching (p, −h) crosses the reference plane at
    # p′ = p − h·tanθ·u and carries cos(2π (u·p′)/P + δ); the reference target sees p′ = p.
    s_um, period, theta = 20.0, 900.0, 35.0
    rows, cols = np.mgrid[0:24, 0:32]
    px, py = cols * s_um, rows * s_um
    h = 150.0 * np.sin(px / 200.0) + 0.5 * py  # |h| < P/(2 tanθ): no unwrapping needed
    phi = np.deg2rad(azimuth_deg)
    u = (np.sin(phi), np.cos(phi))
    shift = h * np.tan(np.deg2rad(theta))

    def frames(hshift):
        up = u[0] * (px - hshift * u[0]) + u[1] * (py - hshift * u[1])
        return np.stack(
            [
                0.4 * (1 + 0.8 * np.cos(2 * np.pi * up / period + d))
                for d in np.deg2rad([0, 90, 180, 270])
            ]
        )

    dpsi = phase_difference(
        four_step_phase(frames(shift)).phase_rad, four_step_phase(frames(0.0)).phase_rad
    )
    est = height_from_phase(dpsi, period_um=period, polar_deg=theta)
    np.testing.assert_allclose(est, h, atol=0.05)


def test_consensus_drops_a_precise_minority_azimuth_off_by_a_fringe_order():
    rng = np.random.default_rng(7)
    a, shape = 4, (60, 60)
    truth = rng.uniform(-500, 500, shape)
    sigma = np.array([3.0, 3.0, 6.0, 6.0])[:, None, None] * np.ones((a,) + shape)
    heights = truth[None] + rng.normal(0.0, 1.0, (a,) + shape) * sigma
    # Azimuth 0 claims the best precision but has a wrong order (+214 µm, one finest period
    # at 45°) on the left third; a weighted median would follow it where it outweighs others.
    sigma[0, :, :20] = 0.5
    heights[0, :, :20] = truth[:, :20] + 214.0 + rng.normal(0.0, 0.5, (60, 20))
    # Rows 0–9: only azimuths 2 and 3, which disagree by an order: no majority → NaN.
    heights[:2, :10] = np.nan
    heights[3, :10] += 214.0
    # Rows 10–19: a single azimuth sees the pixel; taken as it is.
    heights[1:, 10:20] = np.nan
    res = consensus_azimuths(heights, sigma)
    assert np.all(np.isnan(res.height_um[:10]))
    np.testing.assert_allclose(res.height_um[10:20], heights[0, 10:20], rtol=1e-6)
    assert np.all(res.azimuths_used[10:20] == 1)
    body = res.height_um[20:] - truth[20:]
    n = res.azimuths_used[20:]
    # Inliers: the weighted mean has σ = (Σ 1/σ_a²)^−½ ≤ 3/√2 µm; 6σ over 2,400 pixels.
    assert np.all(np.abs(body) <= 6 * 3.0 / np.sqrt(2))
    # σ of the mean of the inliers: 1/√(Σ 1/σ²) = 3/√(2 + 2/4) on the right (all four).
    np.testing.assert_allclose(np.median(res.sigma_um[20:, 20:]), 3 / np.sqrt(2.5), rtol=0.05)
    # The wrong azimuth never counts; honest azimuths fall outside 4σ·√2-ish only rarely.
    assert np.all(n[:, :20] <= 3)
    assert np.mean(n[:, :20] == 3) > 0.98 and np.mean(n[:, 20:] == 4) > 0.98


def test_consensus_scales_understated_sigmas_from_the_azimuth_pairs():
    rng = np.random.default_rng(8)
    shape = (80, 80)
    truth = rng.uniform(-100, 100, shape)
    # The σ handed in are 3× too small (a model error the phase noise does not show): without
    # the scan-wide factor most honest azimuths would disagree at 4σ.
    heights = truth[None] + rng.normal(0.0, 6.0, (3,) + shape)
    res = consensus_azimuths(heights, np.full((3,) + shape, 2.0))
    assert np.mean(res.azimuths_used == 3) > 0.95


def test_consensus_rejects_bad_input():
    with pytest.raises(ValueError, match="sigma_um"):
        consensus_azimuths(np.zeros((2, 3, 3)), np.zeros((2, 3, 4)))
    with pytest.raises(ValueError, match="height_um"):
        consensus_azimuths(np.zeros((3, 3)), np.zeros((3, 3)))


def test_consensus_in_blocks_and_threads_gives_the_same_result(monkeypatch):
    # Pixels are independent: cutting them into blocks (here of 1000 pixels, the last one
    # partial) run in two threads changes nothing, outliers and missing azimuths included.
    import worker.recon.height as height

    rng = np.random.default_rng(22)
    h = rng.normal(100.0, 2.0, (4, 60, 70)).astype(np.float32)
    s = rng.uniform(0.5, 3.0, h.shape).astype(np.float32)
    h[rng.uniform(size=h.shape) < 0.1] += 400.0  # wrong orders
    h[rng.uniform(size=h.shape) < 0.1] = np.nan  # shadowed azimuths
    whole = consensus_azimuths(h, s)
    monkeypatch.setattr(height, "_CONSENSUS_BLOCK", 1000)
    blocks = consensus_azimuths(h, s, workers=2)
    for field in ("height_um", "spread_um", "azimuths_used", "sigma_um"):
        np.testing.assert_array_equal(getattr(blocks, field), getattr(whole, field))


def _consensus_block_plain(hf, sf, valid, k2):
    # Every candidate centre against every azimuth, np.where and take_along_axis: the
    # formulas _consensus_block must reproduce bit for bit.
    hv = np.where(valid, hf, np.float32(0))
    sf2 = np.square(sf)
    wv = np.where(valid, np.float32(1) / sf2, np.float32(0))
    best_n = np.zeros(hf.shape[1], dtype=np.int16)
    best_w = np.zeros(hf.shape[1], dtype=np.float32)
    best = np.full(hf.shape[1], -1, dtype=np.int16)
    for c in range(hf.shape[0]):
        with np.errstate(invalid="ignore", over="ignore"):
            agree = np.square(hv - hv[c]) <= k2 * (sf2 + sf2[c])
        agree &= valid & valid[c]
        n = agree.sum(axis=0, dtype=np.int16)
        wsum = (wv * agree).sum(axis=0)
        better = (n > best_n) | ((n == best_n) & (wsum > best_w))
        best_n = np.where(better, n, best_n)
        best_w = np.where(better, wsum, best_w)
        best = np.where(better, np.int16(c), best)
    index = np.clip(best, 0, None)[None].astype(np.intp)
    centre = np.take_along_axis(hv, index, axis=0)
    sc2 = np.take_along_axis(sf2, index, axis=0)
    with np.errstate(invalid="ignore", over="ignore"):
        inl = valid & (np.square(hv - centre) <= k2 * (sf2 + sc2))
    solved = (best >= 0) & ((best_n >= 2) | (valid.sum(axis=0) == 1))
    inl &= solved[None]
    wi = np.where(inl, wv, np.float32(0))
    wsum = wi.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = (wi * hv).sum(axis=0) / wsum
        var = (wi * np.square(hv - mean[None])).sum(axis=0) / wsum
        sigma = np.where(solved, np.float32(1) / np.sqrt(wsum), np.float32(np.nan))
    return (
        np.where(solved, mean, np.nan).astype(np.float32),
        np.where(solved, np.sqrt(np.maximum(var, 0.0)), np.nan).astype(np.float32),
        inl.sum(axis=0).astype(np.int16),
        sigma.astype(np.float32),
    )


@pytest.mark.parametrize("azimuths", [1, 2, 3, 4, 6])
def test_consensus_block_gives_the_plain_formulas_bit_for_bit(azimuths):
    from worker.recon.height import _consensus_block

    rng = np.random.default_rng(azimuths)
    n = 5000
    h = rng.normal(0.0, 1.0, n).astype(np.float32) + rng.normal(0.0, 0.3, (azimuths, n))
    h[:, ::7] += rng.choice([-8.0, 0.0, 8.0], (azimuths, h[:, ::7].shape[1]))  # wrong orders
    h = h.astype(np.float32)
    s = rng.uniform(0.05, 0.6, (azimuths, n)).astype(np.float32)
    s[:, ::11] = s[:, :1]  # ties in the weights
    h[rng.random(h.shape) < 0.15] = np.nan
    s[rng.random(s.shape) < 0.05] = np.inf
    valid = np.isfinite(h) & np.isfinite(s) & (s > 0)
    sf = np.where(valid, s, np.float32(np.inf))
    k2 = np.float32(16.0)
    got = _consensus_block(h, sf, valid, k2)
    expected = _consensus_block_plain(h, sf, valid, k2)
    for g, e in zip(got, expected, strict=True):
        assert g.dtype == e.dtype
        np.testing.assert_array_equal(g.view(np.uint8), e.view(np.uint8))


def _guard_scene(seed):
    """Rolling ground with a chip (a 400 µm deep pit) and a speckle of fused outliers."""
    rng = np.random.default_rng(seed)
    rows, cols = 60, 80
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
    truth = 200 * np.sin(x / 9) + 100 * np.cos(y / 7)
    truth[20:32, 30:45] -= 400.0
    fringe = truth + rng.normal(0, 3, truth.shape).astype(np.float32)
    sigma = np.full(truth.shape, 3.0, np.float32)
    fringe[22:30, 32:43] = np.nan  # the chip's floor: shadowed for every azimuth
    fused = truth.copy()
    speckle = rng.random(truth.shape) < 0.01
    fused[speckle] += rng.choice([-1, 1], int(speckle.sum())) * rng.uniform(1e3, 1e5, speckle.sum())
    fused[25, 35:38] = 120_000.0  # a needle inside the chip
    fused[10, 10] = truth[10, 10] + 45.0  # within the floor: kept
    return fused.astype(np.float32), fringe.astype(np.float32), sigma, truth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_guard_leaves_no_unsupported_height(seed):
    from worker.recon.height import GUARD_FRINGE, GUARD_NEIGHBOURHOOD, guard_heights

    fused, fringe, sigma, truth = _guard_scene(seed)
    mask = np.ones(fused.shape, bool)
    g = guard_heights(fused, fringe, sigma, mask)
    has_f = np.isfinite(fringe)
    tol = np.maximum(5 * sigma, 50.0)
    # The rule, pixel by pixel: near the fringes where they exist ...
    assert np.all(np.abs(g.height_um - fringe)[has_f] <= tol[has_f] + 1e-3)
    # ... and within the range of the fringe-bounded heights around the pit's floor.
    lo, hi = (
        np.nanmin(np.where(has_f, g.height_um, np.nan)[16:36, 26:49]),
        np.nanmax(np.where(has_f, g.height_um, np.nan)[16:36, 26:49]),
    )
    floor = ~has_f
    assert np.all((g.height_um[floor] >= lo - 1e-3) & (g.height_um[floor] <= hi + 1e-3))
    assert np.all(g.flag[25, 35:38] == GUARD_NEIGHBOURHOOD)
    assert g.flag[10, 10] == 0 and g.height_um[10, 10] == fused[10, 10]
    # Every outlier flagged; nothing else changed.
    bad = np.abs(fused - truth) > 1e3
    assert np.all(g.flag[bad] > 0)
    np.testing.assert_array_equal(g.height_um[g.flag == 0], fused[g.flag == 0])
    assert set(np.unique(g.flag)) <= {0, GUARD_FRINGE, GUARD_NEIGHBOURHOOD}
    # Replaced pixels come from their neighbourhood: near the truth, not at the bound.
    assert np.median(np.abs(g.height_um - truth)[g.flag > 0]) < 30.0


def test_valid_fringe_excludes_rim_single_azimuth_and_lone_outliers():
    from worker.recon.height import valid_fringe

    f = np.zeros((20, 20), np.float32)
    f[10, 10] = 5_000.0  # a lone wrong order
    used = np.full(f.shape, 3, np.int16)
    used[5, 5] = 1
    mask = np.ones(f.shape, bool)
    v = valid_fringe(f, mask, azimuths_used=used, pixel_size_um=50.0)
    assert not v[10, 10] and not v[5, 5]
    assert not v[:2].any() and not v[:, -2:].any()  # the rim
    # The lone wrong order's 8 neighbours too: their 3×3 spans it (as at a cliff).
    assert v[2:-2, 2:-2].sum() == 16 * 16 - 2 - 8
    assert not v[9:12, 9:12].any()


def test_valid_fringe_leaves_out_a_cliff_side_reported_by_the_other_side():
    # A 1 mm cliff whose lower side's first two pixels report the upper side's height (a
    # mixed phase every azimuth agrees on, hard noise 512×384): they pass the 5×5 median
    # test, but near the cliff no fringe height is held to (hard-512 lost RMS 10.8 → 13.9).
    from worker.recon.height import guard_heights, valid_fringe

    rows, cols = 30, 40
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float32)
    truth = np.where(x < 20, 1000.0, 0.0).astype(np.float32) + 2 * y
    fringe = truth.copy()
    fringe[:, 20] += 1000.0  # the lower side's wall pixels report the upper side ...
    fringe[::2, 21] = np.nan  # ... next to pixels no azimuth measured
    mask = np.ones(truth.shape, bool)
    used = np.full(truth.shape, 2, np.int16)
    v = valid_fringe(fringe, mask, azimuths_used=used, pixel_size_um=26.8)
    assert not v[:, 20].any()
    assert v[2:-2, 3:18].all() and v[2:-2, 23:-2].all()
    g = guard_heights(truth, fringe, None, mask, valid=v, pixel_size_um=26.8)
    np.testing.assert_array_equal(g.height_um, truth)  # the right fused side is kept
