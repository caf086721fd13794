import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from worker.recon.fringe import carre_phase, four_step_phase, intensity_noise, phase_sigma_rad
from worker.recon.height import height_from_phase
from worker.recon.unwrap import (
    noise_aware_unwrap,
    paper_consistent_unwrap,
    phase_difference,
    temporal_unwrap,
    wrap_phase,
)

DELTAS = np.deg2rad([0.0, 90.0, 180.0, 270.0])


def test_wrap_phase_range():
    x = np.array([-np.pi, np.pi, 3 * np.pi, -3.5 * np.pi, 0.25], dtype=np.float64)
    w = wrap_phase(x)
    np.testing.assert_allclose(w, [np.pi, np.pi, np.pi, 0.5 * np.pi, 0.25], atol=1e-12)
    assert np.all((w > -np.pi) & (w <= np.pi))


def _fringe_set(psi, a, m, rng, sense):
    return sense(np.stack([a * (1 + m * np.cos(psi + d)) for d in DELTAS]), rng)


def test_temporal_unwrap_recovers_a_surface_spanning_many_fine_periods(
    recon_sphere, recon_sense, recon_sigma, recon_noise
):
    rng = np.random.default_rng(3)
    theta = 45.0
    tan_t = np.tan(np.deg2rad(theta))
    scene = recon_sphere(64, radius_px=40.0, pixel_size_um=40.0)
    # Cap height 800 µm plus a tilt of ±600 µm: |h| ≤ 1400 µm; 8 doubling periods down to
    # 32 µm, i.e. up to 44 fringes of the finest period across the relief.
    xx = np.arange(64)[None, :] * np.ones((64, 1))
    h = scene.height_um + (xx - 31.5) / 31.5 * 600.0
    periods = 4096.0 / 2.0 ** np.arange(8)
    assert periods[0] > 2 * tan_t * np.abs(h).max()  # the spec's unambiguity condition
    m = recon_noise["modulation"]
    a_obj = rng.uniform(0.2, 0.4, h.shape)  # ρ·n·l varies over the object
    u_dot_p = rng.uniform(0, 1e4, h.shape)  # arbitrary pattern coordinate per pixel
    diffs = []
    for p in periods:
        psi_ref = 2 * np.pi * u_dot_p / p + 1.3
        dpsi = -2 * np.pi * h * tan_t / p
        o = four_step_phase(_fringe_set(psi_ref + dpsi, a_obj, m, rng, recon_sense)).phase_rad
        r = four_step_phase(_fringe_set(psi_ref, 0.45, m, rng, recon_sense)).phase_rad
        diffs.append(phase_difference(o, r))
    res = temporal_unwrap(np.stack(diffs), periods)
    h_est = height_from_phase(res.dpsi_rad, period_um=periods[-1], polar_deg=theta)
    # σ_ψ of 4-step ≈ σ_I/(√2·B) per set (σ_I at the mean level, B = m·A); the difference
    # adds object and reference variances; σ_h = σ_Δψ·P/(2π tanθ).
    sig_o = recon_sigma(a_obj) / (np.sqrt(2) * m * a_obj)
    sig_r = recon_sigma(0.45) / (np.sqrt(2) * m * 0.45)
    sig_h = np.sqrt(sig_o**2 + sig_r**2) * periods[-1] / (2 * np.pi * tan_t)
    # A wrong order would be an error of ≥ P_fine/tanθ = 32 µm ≈ 200 σ_h.  5.5σ over 4,096
    # pixels is exceeded by chance with probability ~1e-4.
    assert np.all(np.abs(h_est - h) <= 5.5 * sig_h)
    assert np.all(res.order_residual < 0.1)


def test_temporal_unwrap_flags_a_corrupted_level():
    periods = np.array([800.0, 400.0, 200.0])
    dpsi_fine = np.linspace(-12, 12, 50)[None, :] * np.ones((4, 1))  # coarsest within ±3 rad
    levels = np.stack([dpsi_fine * 200 / p for p in periods])
    levels[1, 0, :] += np.pi  # half a fringe off on one row of the middle level
    res = temporal_unwrap(wrap_phase(levels), periods)
    np.testing.assert_allclose(res.dpsi_rad[1:], dpsi_fine[1:], atol=1e-4)
    assert np.all(res.order_residual[0] > 0.24)
    assert np.all(res.order_residual[1:] < 1e-4)


def test_temporal_unwrap_stops_where_the_fringes_fade():
    periods = np.array([800.0, 400.0, 200.0, 100.0])
    dpsi_fine = np.linspace(-20, 20, 30)[None, :] * np.ones((6, 1))  # in units of P = 100
    levels = np.stack([dpsi_fine * 100 / p for p in periods])
    mod = np.full(levels.shape, 0.8)
    # The finest period is not resolved anywhere (its wrapped phase is garbage) and the
    # 200 µm level is in shadow on row 0.
    levels[3] = np.random.default_rng(0).uniform(-np.pi, np.pi, levels[3].shape)
    mod[3] = 0.02
    mod[2, 0] = 0.05
    res = temporal_unwrap(wrap_phase(levels), periods, modulation=mod)
    np.testing.assert_allclose(res.dpsi_rad, dpsi_fine, atol=1e-4)
    np.testing.assert_array_equal(res.level_used[1:], 2)
    np.testing.assert_array_equal(res.level_used[0], 1)
    # Weight (m·P_fine/P_used)²: 0.8·100/200 on rows 1.., 0.8·100/400 on row 0.
    np.testing.assert_allclose(res.weight[1:], 0.16, rtol=1e-5)
    np.testing.assert_allclose(res.weight[0], 0.04, rtol=1e-5)


def test_paper_consistent_unwrap_on_mod_pi_carre_phases():
    # Quarter-period schedule: the coarsest difference stays within ±π/2; periods double.
    periods = 3200.0 / 2.0 ** np.arange(6)
    dpsi0 = np.linspace(-1.4, 1.4, 40)[None, :] * np.ones((5, 1))
    psi_ref = np.linspace(0, 9, 40)[::-1][None, :] * np.ones((5, 1))
    half = []
    for p in periods:
        d = dpsi0 * periods[0] / p
        o = np.stack([0.4 * (1 + 0.8 * np.cos(psi_ref + d + s)) for s in DELTAS])
        r = np.stack([0.5 * (1 + 0.8 * np.cos(psi_ref + s)) for s in DELTAS])
        po = carre_phase(o, quadrant="paper").phase_rad
        pr = carre_phase(r, quadrant="paper").phase_rad
        half.append(wrap_phase(po - pr, cycle_rad=np.pi))
    res = paper_consistent_unwrap(np.stack(half), periods)
    np.testing.assert_allclose(res.dpsi_rad, dpsi0 * periods[0] / periods[-1], atol=1e-3)


@pytest.mark.parametrize(
    ("wrapped", "periods", "culprit"),
    [
        (np.zeros((2, 4, 4)), [100.0, 200.0], "period_um"),
        (np.zeros((2, 4, 4)), [100.0], "period_um"),
        (np.zeros((2, 4, 4)), [100.0, -1.0], "period_um"),
        (np.zeros((4, 4)), [100.0], "wrapped_rad"),
    ],
)
def test_temporal_unwrap_rejects_bad_input(wrapped, periods, culprit):
    with pytest.raises(ValueError, match=culprit):
        temporal_unwrap(wrapped, periods)


def test_phase_difference_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="reference_rad"):
        phase_difference(np.zeros((3, 3)), np.zeros((3, 4)))


@pytest.mark.slow
@pytest.mark.xdist_group("recon_sim")
def test_simulated_bundle_heights_against_ground_truth(simulated_recon):
    r = simulated_recon
    e = r.height_um - r.gt_height_um
    z = np.abs(e[r.smooth]) / r.sigma_height_um[r.smooth]
    assert np.mean(np.isfinite(z)) > 0.99
    # |e|/σ of a Gaussian: median 0.67, 99th percentile 2.6.
    assert np.nanmedian(z) < 1.5
    assert np.nanpercentile(z, 99) < 5.0


@given(
    h_frac=st.floats(-0.49, 0.49),
    n_levels=st.integers(1, 9),
    ratio=st.sampled_from([2.0, 3.0, 4.0]),
)
def test_temporal_unwrap_is_exact_without_noise(h_frac, n_levels, ratio):
    # Any height within the spec's unambiguity limit |Δψ_0| < π comes back exactly.
    periods = 1000.0 / ratio ** np.arange(n_levels)
    dpsi0 = 2 * np.pi * h_frac
    levels = np.array([dpsi0 * periods[0] / p for p in periods])[:, None, None]
    res = temporal_unwrap(wrap_phase(levels), periods)
    expected = dpsi0 * periods[0] / periods[-1]
    np.testing.assert_allclose(res.dpsi_rad[0, 0], expected, rtol=1e-5, atol=1e-3)


@given(
    h_frac=st.floats(-0.49, 0.49),
    n_levels=st.integers(1, 9),
    ratio=st.sampled_from([2.0, 3.0, 4.0]),
)
def test_noise_aware_unwrap_is_exact_without_noise(h_frac, n_levels, ratio):
    periods = 1000.0 / ratio ** np.arange(n_levels)
    dpsi0 = 2 * np.pi * h_frac
    levels = np.array([dpsi0 * periods[0] / p for p in periods])[:, None, None]
    # Tiny σ: every order is unambiguous, so every level is used.  The coarsest must stay
    # z·σ from ±π, and with ratio 4 fix the next level: σ·z·4 < π.
    sig = np.full(levels.shape, 1e-4)
    # Exact synthetic phases: no model error to allow for.
    res = noise_aware_unwrap(wrap_phase(levels), sig, periods, model_sigma_rad=0.0)
    expected = dpsi0 * periods[0] / periods[-1]
    if np.pi - abs(dpsi0) < 3.8e-4:
        return  # within z·σ of ±π: legitimately refused
    np.testing.assert_allclose(res.dpsi_rad[0, 0], expected, rtol=1e-5, atol=1e-3)
    assert res.level_used[0, 0] == n_levels - 1
    assert res.conflicts[0, 0] == 0


def test_noise_aware_unwrap_skips_an_unusable_level_and_flags_a_corrupt_one():
    periods = np.array([800.0, 400.0, 200.0, 100.0, 50.0])
    dpsi_fine = np.linspace(-40, 40, 60)[None, :] * np.ones((6, 1))  # in units of P = 50
    levels = np.stack([dpsi_fine * 50 / p for p in periods])
    sig = np.full(levels.shape, 0.01)
    # Row 0: the 200 µm level is in shadow there (σ = inf, its phase garbage).  Row 1: the
    # 100 µm level is off by π/2 (an interreflection) although it looks precise.  Row 2:
    # the finest level is not resolved (σ 0.5: above the detection bound, never used).
    levels[2, 0] = 3.0
    sig[2, 0] = np.inf
    levels[3, 1] += np.pi / 2
    sig[4, 2] = 0.5
    levels[4, 2] = np.random.default_rng(0).uniform(-np.pi, np.pi, levels.shape[2])
    res = noise_aware_unwrap(wrap_phase(levels), sig, periods, model_sigma_rad=0.0)
    # σ of the estimate: 0.01 rad at the finest level, combined with the coarser ones.
    np.testing.assert_allclose(res.dpsi_rad[[0, 1, 3, 4, 5]], dpsi_fine[[0, 1, 3, 4, 5]], atol=0.1)
    # Row 2 stops at the 100 µm level: its σ is twice the finest-level one, scaled.
    np.testing.assert_allclose(res.dpsi_rad[2], dpsi_fine[2], atol=0.2)
    np.testing.assert_array_equal(res.level_used[2], 3)
    np.testing.assert_array_equal(res.level_used[[0, 1, 3]], 4)
    np.testing.assert_array_equal(res.conflicts[1], 1)
    np.testing.assert_array_equal(res.conflicts[[0, 2, 3]], 0)
    # Inverse variances add: Σ (q_i/σ_i)² over the used levels, q_i = P_fine/P_i.
    q = 50.0 / periods
    np.testing.assert_allclose(res.sigma_rad[3], 0.01 / np.sqrt(np.sum(q**2)), rtol=1e-4)
    np.testing.assert_allclose(res.sigma_rad[2], 0.01 / np.sqrt(np.sum(q[:4] ** 2)), rtol=1e-4)


def _scene_levels(rng, sense, shape, periods, tan_t, h, a_obj, attenuation):
    """Object/reference 4-step sets per period through the noise model; σ from the data."""
    diffs, sigs = [], []
    u_dot_p = rng.uniform(0, 1e4, shape)
    for i, p in enumerate(periods):
        psi_ref = 2 * np.pi * u_dot_p / p + 0.7
        m = MODULATION * attenuation[i]
        dpsi = -2 * np.pi * h * tan_t / p
        o = four_step_phase(_fringe_set(psi_ref + dpsi, a_obj, m, rng, sense))
        r = four_step_phase(_fringe_set(psi_ref, 0.45, m, rng, sense))
        s_o = phase_sigma_rad(o, intensity_noise(o.mean, o.residual))
        s_r = phase_sigma_rad(r, intensity_noise(r.mean, r.residual))
        diffs.append(phase_difference(o.phase_rad, r.phase_rad))
        sigs.append(np.sqrt(s_o**2 + s_r**2))
    return np.stack(diffs), np.stack(sigs)


MODULATION = 0.85


def test_noise_aware_unwrap_has_no_gross_errors_at_low_modulation(recon_sense):
    rng = np.random.default_rng(21)
    shape = (96, 96)
    theta = 45.0
    tan_t = np.tan(np.deg2rad(theta))
    yy, xx = np.mgrid[0:96, 0:96]
    h = 900.0 * np.sin(xx / 9.0) * np.cos(yy / 13.0) + 8.0 * (xx - 48)
    periods = 8192.0 / 2.0 ** np.arange(8)  # down to 64 µm: ~90 fine fringes over the relief
    assert periods[0] > 2 * tan_t * np.abs(h).max()
    # Columns 0–23 lit (ρ·n·l = 0.3); 24–47 dim clay (0.004: σ_ψ ≈ 0.15 rad), rows 48–95 of
    # it darker still (0.0006: σ_ψ ≈ 0.7 rad, where the chain's 2π orders fail); 48–71 cast
    # shadow (nothing but read noise); 72–95 lit with the two finest periods blurred away
    # (modulation × 0.02, as on a steep wall).
    dim_a = np.where(yy < 48, 0.004, 0.0006)
    a_obj = np.select([xx < 24, xx < 48, xx < 72], [0.3, dim_a, 0.0], 0.3).astype(float)
    att = np.ones((8,) + shape)
    att[6:, :, 72:] = 0.02
    diffs, sigs = _scene_levels(rng, recon_sense, shape, periods, tan_t, h, a_obj, att)
    res = noise_aware_unwrap(diffs, sigs, periods)
    chain = temporal_unwrap(diffs, periods)
    truth = -2 * np.pi * h * tan_t / periods[-1]
    err = res.dpsi_rad - truth
    lit = xx < 24
    dim = (xx >= 26) & (xx < 46) & (yy < 46)
    dark = (xx >= 26) & (xx < 46) & (yy >= 50)
    shadow = (xx >= 50) & (xx < 70)  # away from the 5×5 noise window's reach
    blurred = xx >= 74
    # Wrong orders would be errors ≥ 2π·P_fine/P_level ≥ 2π; the noise is σ_rad.  6σ over
    # 9,216 pixels is exceeded by chance with probability ~2e-5.  The local 5×5 noise term
    # only makes σ larger, so this bound is conservative in its favour — hence the second
    # check that σ is not absurdly large where the fringes are good.
    fin = np.isfinite(err)
    assert np.all(np.abs(err[fin]) <= 6.0 * res.sigma_rad[fin])
    assert np.mean(fin[lit]) == 1.0 and np.median(res.sigma_rad[lit]) < 0.05
    # Dim clay: all kept.  Darker clay: the chain gets many orders wrong; the pixels kept
    # here are right (checked above) — those the noise forbids are left out.
    assert np.mean(fin[dim]) > 0.99
    assert np.mean(np.abs(chain.dpsi_rad - truth)[dark] > np.pi) > 0.05
    # Shadow: a fringe is "detected" in noise with probability 1e-3 per level; the coarsest
    # must pass and fix the next, and a false start then meets inconsistent levels.
    assert np.mean(fin[shadow]) < 0.01
    # Blurred finest periods: the pixel stops at the third-finest level (index 5).
    assert np.mean(res.level_used[blurred] == 5) > 0.99


def test_noise_aware_unwrap_takes_noise_free_phases():
    # σ = 0 from ideal synthetic frames (no residual, no read noise) must not void the pixel.
    periods = np.array([1000.0, 500.0, 250.0])
    dpsi_fine = np.linspace(-10, 10, 7)[None, :]
    levels = np.stack([dpsi_fine * 250 / p for p in periods])
    res = noise_aware_unwrap(wrap_phase(levels), np.zeros(levels.shape), periods)
    np.testing.assert_allclose(res.dpsi_rad, dpsi_fine, atol=1e-4)
    np.testing.assert_array_equal(res.level_used, 2)


def test_noise_aware_unwrap_allows_for_model_error():
    # Phases with a systematic error of 0.05 rad per level (pattern harmonics, say) and
    # next to no noise: with the default model error 0.03 rad the 4σ test allows
    # 4·0.03·√2 ≈ 0.17 rad of disagreement, so no level is called a conflict.
    periods = np.array([1000.0, 500.0, 250.0, 125.0])
    dpsi_fine = np.linspace(-20, 20, 11)[None, :]
    bias = np.array([0.05, -0.05, 0.05, -0.05])[:, None, None]
    levels = np.stack([dpsi_fine * 125 / p for p in periods]) + bias
    sig = np.full(levels.shape, 1e-4)
    res = noise_aware_unwrap(wrap_phase(levels), sig, periods)
    np.testing.assert_array_equal(res.conflicts, 0)
    np.testing.assert_array_equal(res.level_used, 3)
    strict = noise_aware_unwrap(wrap_phase(levels), sig, periods, model_sigma_rad=0.0)
    assert np.all(strict.conflicts > 0)


def test_noise_aware_unwrap_in_threads_gives_the_same_result():
    # Pixels are independent: blocks of rows shared out between threads change nothing.
    rng = np.random.default_rng(21)
    periods = np.array([64.0, 32.0, 16.0, 8.0])
    truth = rng.uniform(-np.pi, np.pi, (120, 50)) * 0.9  # coarsest level within (−π, π)
    scaled = truth[None] * (periods[0] / periods)[:, None, None]
    sigma = rng.uniform(0.02, 0.6, scaled.shape).astype(np.float32)
    wrapped = wrap_phase((scaled + rng.normal(0, 1, scaled.shape) * sigma).astype(np.float32))
    one = noise_aware_unwrap(wrapped, sigma, periods)
    two = noise_aware_unwrap(wrapped, sigma, periods, workers=2)
    for field in ("dpsi_rad", "order_residual", "level_used", "weight", "sigma_rad", "conflicts"):
        np.testing.assert_array_equal(getattr(two, field), getattr(one, field))


def test_noise_aware_unwrap_without_diagnostics_leaves_only_them_out():
    # order_residual and weight are skipped, every other output keeps its bits (NaN, ∞
    # and zero σ, NaN phases and undetected levels included).
    rng = np.random.default_rng(22)
    periods = np.array([64.0, 32.0, 16.0, 8.0])
    truth = rng.uniform(-np.pi, np.pi, (90, 40)) * 0.9
    scaled = truth[None] * (periods[0] / periods)[:, None, None]
    sigma = rng.uniform(0.0, 0.8, scaled.shape).astype(np.float32)
    wrapped = wrap_phase((scaled + rng.normal(0, 1, scaled.shape) * sigma).astype(np.float32))
    wrapped[0, 30:35] = np.nan
    sigma[:, :5, :5] = 0.0
    sigma[1, 10:20] = np.inf
    sigma[2, 20:30] = np.nan
    full = noise_aware_unwrap(wrapped, sigma, periods)
    bare = noise_aware_unwrap(wrapped, sigma, periods, workers=2, diagnostics=False)
    assert bare.order_residual is None and bare.weight is None
    assert np.isnan(full.dpsi_rad).any() and np.isfinite(full.dpsi_rad).any()
    for field in ("dpsi_rad", "level_used", "sigma_rad", "conflicts"):
        np.testing.assert_array_equal(getattr(bare, field), getattr(full, field))
    finite = np.isfinite(full.dpsi_rad)
    assert np.isnan(full.sigma_rad[~finite]).all() and (full.weight[~finite] == 0).all()
    np.testing.assert_allclose(full.weight[finite], full.sigma_rad[finite] ** -2.0, rtol=1e-6)
