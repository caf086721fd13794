import numpy as np
import pytest

from worker.recon.fringe import (
    FringePhase,
    IntensityNoise,
    carre_phase,
    four_step_phase,
    intensity_noise,
    phase_sigma_rad,
)
from worker.recon.unwrap import wrap_phase

DELTAS = np.deg2rad([0.0, 90.0, 180.0, 270.0])


def _frames(psi, a, m, steps_rad=DELTAS):
    """I_δ = A (1 + m cos(ψ + δ)) for each δ, shape (4, ...)."""
    return np.stack([a * (1.0 + m * np.cos(psi + d)) for d in steps_rad])


def test_four_step_is_exact_on_ideal_frames():
    rng = np.random.default_rng(0)
    psi = rng.uniform(-np.pi, np.pi, (32, 32))
    a = rng.uniform(0.1, 0.6, (32, 32))
    res = four_step_phase(_frames(psi, a, 0.85))
    np.testing.assert_allclose(wrap_phase(res.phase_rad - psi), 0.0, atol=2e-6)
    np.testing.assert_allclose(res.modulation, 0.85, rtol=1e-5)
    np.testing.assert_allclose(res.amplitude, 0.85 * a, rtol=1e-5)
    assert res.phase_rad.dtype == np.float32


def test_four_step_phase_noise_matches_prediction(recon_sense, recon_sigma, recon_noise):
    rng = np.random.default_rng(1)
    shape = (64, 64)
    psi = rng.uniform(-np.pi, np.pi, shape)
    a = rng.uniform(0.2, 0.5, shape)
    ideal = _frames(psi, a, recon_noise["modulation"])
    res = four_step_phase(recon_sense(ideal, rng))
    err = wrap_phase(res.phase_rad.astype(np.float64) - psi)
    # ψ error ≈ (cos ψ·(n270 − n90) − sin ψ·(n0 − n180)) / (2B), B = m·A, so
    # var = (cos²ψ (σ270² + σ90²) + sin²ψ (σ0² + σ180²)) / (4B²) with σ from the noise model.
    s2 = recon_sigma(ideal) ** 2
    b = recon_noise["modulation"] * a
    var = (np.cos(psi) ** 2 * (s2[3] + s2[1]) + np.sin(psi) ** 2 * (s2[0] + s2[2])) / (4 * b**2)
    ratio = np.mean(err**2) / np.mean(var)
    # 4,096 pixels: the mean of err²/var has relative sd sqrt(2/4096) ≈ 2 %; 10 % bound.
    assert 0.9 < ratio < 1.1
    assert np.max(np.abs(err) / np.sqrt(var)) < 5.5


def test_carre_equals_four_step_on_ideal_frames():
    rng = np.random.default_rng(2)
    psi = rng.uniform(-np.pi, np.pi, (32, 32))
    frames = _frames(psi, rng.uniform(0.1, 0.6, (32, 32)), 0.7)
    carre = carre_phase(frames)
    four = four_step_phase(frames)
    np.testing.assert_allclose(wrap_phase(carre.phase_rad - four.phase_rad), 0.0, atol=1e-4)
    np.testing.assert_allclose(carre.median_step_rad, np.pi / 2, atol=1e-5)
    np.testing.assert_allclose(carre.modulation, 0.7, rtol=1e-4)


def test_carre_handles_a_miscalibrated_phase_step():
    rng = np.random.default_rng(3)
    shape = (48, 48)
    # The projector really steps by 78°, not the nominal 90°, on object and reference alike.
    steps = np.deg2rad(78.0) * np.arange(4)
    psi_ref = rng.uniform(-np.pi, np.pi, shape)
    dpsi = rng.uniform(-2.5, 2.5, shape)
    a = rng.uniform(0.2, 0.5, shape)
    obj = _frames(psi_ref + dpsi, a, 0.85, steps)
    ref = _frames(psi_ref, 0.9 * np.ones(shape), 0.85, steps)
    c_obj, c_ref = carre_phase(obj), carre_phase(ref)
    np.testing.assert_allclose(wrap_phase(c_obj.phase_rad - c_ref.phase_rad - dpsi), 0, atol=1e-4)
    np.testing.assert_allclose(np.rad2deg(c_obj.median_step_rad), 78.0, atol=1e-3)
    # The 4-step formula assumes 90° and is off by up to ~6° here: the test can tell them apart.
    f_err = wrap_phase(four_step_phase(obj).phase_rad - four_step_phase(ref).phase_rad - dpsi)
    assert np.max(np.abs(f_err)) > 0.05


def test_carre_paper_mode_is_the_full_phase_modulo_pi():
    rng = np.random.default_rng(4)
    psi = rng.uniform(-np.pi, np.pi, (32, 32))
    frames = _frames(psi, 0.4, 0.85)
    paper = carre_phase(frames, quadrant="paper").phase_rad
    full = carre_phase(frames).phase_rad
    assert np.all(np.abs(paper) <= np.pi / 2 + 1e-6)
    np.testing.assert_allclose(wrap_phase(paper - full, cycle_rad=np.pi), 0.0, atol=1e-4)


def test_carre_noise_stays_near_four_step(recon_sense, recon_noise):
    rng = np.random.default_rng(5)
    shape = (64, 64)
    psi = rng.uniform(-np.pi, np.pi, shape)
    frames = recon_sense(_frames(psi, 0.4, recon_noise["modulation"]), rng)
    e4 = wrap_phase(four_step_phase(frames).phase_rad - psi)
    ec = wrap_phase(carre_phase(frames).phase_rad - psi)
    # Carré uses the same differences as 4-step plus a self-estimated step; with a 90° step
    # its error is of the same order (Servin & Gonzalez 2012 give comparable SNR).  No
    # quadrant flips: a flip would be an error of order π, i.e. ~100 σ here.
    assert np.sqrt(np.mean(ec**2)) < 2.0 * np.sqrt(np.mean(e4**2))
    assert np.max(np.abs(ec)) < 10.0 * np.sqrt(np.mean(e4**2))


@pytest.mark.parametrize(
    ("func", "kwargs", "culprit"),
    [
        (four_step_phase, {}, "frames"),
        (carre_phase, {}, "frames"),
        (carre_phase, {"quadrant": "both"}, "quadrant"),
        (carre_phase, {"nominal_step_deg": 150.0}, "nominal_step_deg"),
    ],
)
def test_fringe_rejects_bad_input(func, kwargs, culprit):
    frames = np.ones((3, 4, 4)) if not kwargs else np.ones((4, 4, 4))
    with pytest.raises(ValueError, match=culprit):
        func(frames, **kwargs)


def test_phase_estimators_leave_their_input_alone():
    rng = np.random.default_rng(9)
    frames = _frames(rng.uniform(-3, 3, (8, 8)), 0.4, 0.8).astype(np.float32)
    before = frames.copy()
    four_step_phase(frames)
    carre_phase(frames)
    carre_phase(frames, quadrant="paper")
    np.testing.assert_array_equal(frames, before)


def test_four_step_mean_and_residual_on_ideal_frames():
    rng = np.random.default_rng(10)
    psi = rng.uniform(-np.pi, np.pi, (16, 16))
    a = rng.uniform(0.1, 0.6, (16, 16))
    res = four_step_phase(_frames(psi, a, 0.8))
    np.testing.assert_allclose(res.mean, a, rtol=1e-5)
    np.testing.assert_allclose(res.residual, 0.0, atol=1e-6)


def test_intensity_noise_recovers_the_photon_transfer_line(recon_sense, recon_noise):
    rng = np.random.default_rng(11)
    shape = (192, 192)
    psi = rng.uniform(-np.pi, np.pi, shape)
    a = rng.uniform(0.02, 0.6, shape)
    res = four_step_phase(recon_sense(_frames(psi, a, recon_noise["modulation"]), rng))
    fit = intensity_noise(res.mean, res.residual)
    # conftest's model: σ² = x/FW + (read/FW)² + q²/12 with x the frame level; the mean of the
    # four frames' variances is linear in A with slope 1/FW.
    fw = recon_noise["full_well_e"]
    full = 2 ** recon_noise["bit_depth"] - 1
    read_var = (recon_noise["read_noise_e"] / fw) ** 2 + 1.0 / (12 * full**2)
    # 36,864 pixels in 12 bins of ~3,000: the median of χ²₁ over a bin is known to ~2.5 %
    # (1.25·sqrt(2/n)·…), the slope over the range of A to a few %; 10 % bound on the slope.
    assert fit.gain == pytest.approx(1.0 / fw, rel=0.1)
    # The intercept is tiny next to the shot noise of the darkest bin (A ≈ 0.04 → 2e-6):
    # only its order of magnitude is testable.
    assert 0.0 <= fit.read_var < 10 * read_var + 0.1 * 0.04 / fw


def test_phase_sigma_predicts_the_phase_error(recon_sense, recon_noise):
    rng = np.random.default_rng(12)
    shape = (96, 96)
    psi = rng.uniform(-np.pi, np.pi, shape)
    a = rng.uniform(0.05, 0.5, shape)
    res = four_step_phase(recon_sense(_frames(psi, a, recon_noise["modulation"]), rng))
    sig = phase_sigma_rad(res, intensity_noise(res.mean, res.residual))
    err = wrap_phase(res.phase_rad.astype(np.float64) - psi)
    # σ_ψ = σ_I/(√2 B): err/σ is N(0, 1).  The local 5×5 residual term can only raise σ (by
    # ~ its own scatter, ±28 % for 25 samples of χ²₁, on the max of two estimates): mean of
    # (err/σ)² between 0.6 and 1.1 (9,216 pixels: sampling sd 1.5 %).
    z2 = np.mean((err / sig) ** 2)
    assert 0.6 < z2 < 1.1
    # The model alone is unbiased.
    sig_m = phase_sigma_rad(res, intensity_noise(res.mean, res.residual), local_px=0)
    assert 0.9 < np.mean((err / sig_m) ** 2) < 1.1


def test_phase_sigma_is_large_where_there_is_no_fringe(recon_sense):
    # A cast shadow: the pixel sees only the read noise (A ≈ 0, B ≈ 0).  Whatever B the noise
    # fakes, B²/σ_I² is Exp(1)-distributed, so σ_ψ = σ_I/(√2 B) < 0.27 rad (B²/σ_I² > 6.9)
    # happens with probability e^−6.9 = 1e-3; over 1,024 dark pixels at most a few percent.
    rng = np.random.default_rng(13)
    shape = (64, 64)
    psi = rng.uniform(-np.pi, np.pi, shape)
    a = np.where(np.arange(64)[None, :] < 16, 0.0, 0.4) * np.ones(shape)
    res = four_step_phase(recon_sense(_frames(psi, a, 0.85), rng))
    sig = phase_sigma_rad(res, intensity_noise(res.mean, res.residual))
    dark = sig[:, 2:14]  # away from the 5×5 window's reach into the lit part
    assert np.mean(dark < 0.27) < 0.01
    assert np.median(sig[:, 20:]) < 0.02


def test_intensity_noise_variance_is_the_line():
    n = IntensityNoise(read_var=1e-6, gain=2e-5)
    np.testing.assert_allclose(n.variance(np.array([0.0, 0.5, -1.0])), [1e-6, 1.1e-5, 1e-6])


def test_phase_sigma_ignores_the_patterns_second_harmonic(recon_sense, recon_sigma):
    # An uncorrected projector gamma (2.2) distorts the sinusoid: its second harmonic fills
    # the 4-step residual although the phase is blind to it.  With the phase given, the
    # harmonic is fitted and removed, and σ_ψ stays what the camera noise implies.
    rng = np.random.default_rng(14)
    shape = (96, 96)
    psi = rng.uniform(-np.pi, np.pi, shape)
    a = rng.uniform(0.1, 0.4, shape)
    pattern = np.stack([(0.5 * (1 + 0.85 * np.cos(psi + d))) ** 2.2 for d in DELTAS])
    res = four_step_phase(recon_sense(2.0 * a * pattern, rng))
    with_phase = intensity_noise(res.mean, res.residual, phase_rad=res.phase_rad)
    blind = intensity_noise(res.mean, res.residual)
    assert with_phase.harmonic != (0.0, 0.0)
    sig = phase_sigma_rad(res, with_phase)
    sig_blind = phase_sigma_rad(res, blind)
    # The same frames' noise through the ideal σ_I (conftest's model at the mean level):
    # the 5×5 local term lifts σ by ≲ 15 % on average (max of two estimates); 1.3× bound.
    # The fit leaves the harmonic's higher orders (6th, …) behind, bounded and non-Gaussian,
    # which bias the bins' median-based σ_I² low (0.77 here): 0.6 bound below.
    ideal = np.sqrt(0.5 * recon_sigma(res.mean) ** 2) / res.amplitude
    assert 0.6 < np.median(sig / ideal) < 1.3
    assert np.median(sig_blind / ideal) > 2.0
    err = wrap_phase(res.phase_rad.astype(np.float64) - psi)
    # The phase itself: the harmonic does not bias it; odd harmonics do, slightly (a few
    # σ at most here), so only the order of magnitude is checked.
    assert np.sqrt(np.mean(err**2)) < 3 * np.median(sig)


def test_four_step_without_modulation_leaves_the_rest_unchanged():
    rng = np.random.default_rng(23)
    frames = _frames(rng.uniform(-3, 3, (8, 8)), 0.4, 0.8).astype(np.float32)
    frames[:, 0, 0] = 0.0  # A = 0: modulation NaN there when asked for
    full = four_step_phase(frames)
    bare = four_step_phase(frames, modulation=False)
    assert bare.modulation is None and np.isnan(full.modulation[0, 0])
    for field in ("phase_rad", "amplitude", "mean", "residual"):
        np.testing.assert_array_equal(getattr(bare, field), getattr(full, field))


@pytest.mark.parametrize("n", [24, 35, 1000, 20_011])
def test_bin_medians_are_those_of_the_array_split_bins(n):
    # intensity_noise's 12 quantile bins: two block medians give the per-bin values exactly.
    from worker.recon.fringe import _bin_medians

    rng = np.random.default_rng(n)
    a = rng.random(n)
    a[::5] = 0.5  # ties
    b = rng.random(n) ** 2
    order = np.argsort(a)
    bins = np.array_split(order, 12)
    xa, yv = _bin_medians(a[order], b[order], 12)
    np.testing.assert_array_equal(xa, [np.median(a[i]) for i in bins])
    np.testing.assert_array_equal(yv, [np.median(b[i]) for i in bins])


def test_four_step_in_blocks_of_rows_gives_the_whole_frame_formulas():
    # Rows are processed in cache-sized blocks (the last one partial): each pixel must get
    # the float32 values of the whole-frame expressions, bit for bit, whatever its block.
    from worker.recon.fringe import _BLOCK_PIXELS

    rng = np.random.default_rng(31)
    cols = 1000
    rows = 2 * (_BLOCK_PIXELS // cols) + 5
    frames = rng.uniform(0.0, 1.0, (4, rows, cols)).astype(np.float32)
    frames[:, -1, :3] = 0.0  # A = 0 in the last, partial block: modulation NaN
    frames[:, 0, :3] -= 2.0  # A < 0 (dark-subtracted noise): NaN as well
    frames[1, 0, 3] = np.nan  # NaN frames: NaN
    res = four_step_phase(frames)
    i0, i90, i180, i270 = frames
    s, c = i270 - i90, i0 - i180
    amp = np.sqrt(s * s + c * c) * np.float32(0.5)
    mean = ((i0 + i180) + (i90 + i270)) * np.float32(0.25)
    np.testing.assert_array_equal(res.phase_rad, np.arctan2(s, c))
    np.testing.assert_array_equal(res.amplitude, amp)
    np.testing.assert_array_equal(res.mean, mean)
    np.testing.assert_array_equal(res.residual, ((i0 + i180) - (i90 + i270)) * np.float32(0.5))
    with np.errstate(divide="ignore", invalid="ignore"):
        np.testing.assert_array_equal(res.modulation, np.where(mean > 0, amp / mean, np.nan))
    assert np.isnan(res.modulation[-1, :3]).all() and np.isnan(res.modulation[0, :4]).all()
    # Written into a previous result's modulation, blocks and all: the same bits.
    again = four_step_phase(frames, out=FringePhase(None, np.zeros_like(res.modulation), None))
    np.testing.assert_array_equal(again.modulation.view(np.int32), res.modulation.view(np.int32))


def test_four_step_writes_into_the_arrays_of_out():
    # A previous result's arrays are written over (no fresh arrays); its None fields are
    # allocated; the values are those of a call without out.
    rng = np.random.default_rng(37)
    frames = rng.uniform(0.0, 1.0, (4, 40, 30)).astype(np.float32)
    fresh = four_step_phase(frames)
    old = four_step_phase(rng.uniform(0.0, 1.0, (4, 40, 30)).astype(np.float32))
    out = four_step_phase(frames, out=FringePhase(old.phase_rad, None, None, old.mean))
    assert out.phase_rad is old.phase_rad and out.mean is old.mean
    assert out.amplitude is not old.amplitude and out.residual is not old.residual
    for field in ("phase_rad", "modulation", "amplitude", "mean", "residual"):
        np.testing.assert_array_equal(getattr(out, field), getattr(fresh, field))
    with pytest.raises(ValueError, match="out.mean"):
        four_step_phase(frames, out=FringePhase(None, None, None, np.empty((40, 31), np.float32)))
    with pytest.raises(ValueError, match="out.modulation must be C-contiguous"):
        four_step_phase(frames, out=FringePhase(None, np.empty((30, 40), np.float32).T, None))


@pytest.mark.parametrize("harmonic", [(0.0, 0.0), (0.02, -0.01)])
def test_phase_sigma_written_into_out_gives_the_formulas(harmonic):
    # The local mean of r² is formed in the output array, which is then written over: each
    # pixel must get the float32 values of the plain expressions, bit for bit.
    import cv2

    rng = np.random.default_rng(41)
    rows, cols = 37, 50
    frames = rng.uniform(0.0, 1.0, (4, rows, cols)).astype(np.float32)
    frames[:, -1, :3] = 0.0  # B = 0: σ = inf
    frames[:, 0, 7] = np.nan
    res = four_step_phase(frames)
    noise = IntensityNoise(read_var=1e-4, gain=2e-3, harmonic=harmonic)
    var = np.maximum(res.mean, np.float32(0)) * np.float32(noise.gain)
    var += np.float32(noise.read_var)
    two_psi = 2.0 * res.phase_rad
    fit = np.cos(two_psi) * np.float32(harmonic[0]) + np.sin(two_psi) * np.float32(harmonic[1])
    r = res.residual - fit * res.mean if harmonic != (0.0, 0.0) else res.residual
    local = cv2.blur(np.square(r), (5, 5), borderType=cv2.BORDER_REFLECT)
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = np.sqrt(np.fmax(var, local) * np.float32(0.5)) / res.amplitude
        expected_model = np.sqrt(var * np.float32(0.5)) / res.amplitude
    out = np.full((rows, cols), 7.0, np.float32)
    assert phase_sigma_rad(res, noise, out=out) is out
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(phase_sigma_rad(res, noise), expected)
    np.testing.assert_array_equal(phase_sigma_rad(res, noise, local_px=0), expected_model)
    assert np.isinf(out[-1, :3]).all() and np.isnan(out[0, 7])
