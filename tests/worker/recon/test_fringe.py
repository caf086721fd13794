import numpy as np
import pytest

from worker.recon.fringe import carre_phase, four_step_phase
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
