"""The simulated frames obey SCAN_BUNDLE.md's "What a pixel measures" (clean preset)."""

from __future__ import annotations

import numpy as np
import pytest

from worker.simulate.noise import noise_model
from worker.simulate.rig import FrameSpec, Rig, render_frame
from worker.simulate.shadow import cast_shadow
from worker.simulate.view import flat_view, sample_coords_um

W, H, S, SS = 40, 32, 100.0, 2  # small frame: 4 × 3.2 mm at 100 µm, 2×2 samples per pixel
CLEAN = noise_model("clean")
POLAR = 45.0


def _rig() -> Rig:
    return Rig(7, W * S, H * S, irradiance_variation=0.15)


def _radiance(view, frame: FrameSpec, rig: Rig) -> np.ndarray:
    """Read back as a conforming reader would: clean has no offset, gamma 1, exposure 1."""
    raw = render_frame(view, frame, CLEAN, np.random.default_rng(0), rig=rig)
    return raw.astype(np.float64) / CLEAN.max_value


def _plane_view(gx: float, gy: float, h0_um: float, albedo: float):
    xs = sample_coords_um(W, S, SS)[None, :]
    ys = sample_coords_um(H, S, SS)[:, None]
    h = h0_um + gx * xs + gy * ys
    n = np.array([-gx, -gy, -1.0]) / np.linalg.norm([gx, gy, 1.0])
    normals = np.broadcast_to(n, (*h.shape, 3))
    return flat_view(W, H, S, SS, height_ss_um=h, normals_ss=normals, albedo=albedo), n


def _light(azimuth_deg: float) -> np.ndarray:
    phi, th = np.radians(azimuth_deg), np.radians(POLAR)
    return np.array([np.sin(th) * np.sin(phi), np.sin(th) * np.cos(phi), -np.cos(th)])


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 135.0, 270.0])
def test_tilted_plane_gives_lambertian_ratio(azimuth_deg):
    gx, gy, h0, rho = 0.3, -0.2, 600.0, 0.4
    view, n = _plane_view(gx, gy, h0, rho)
    rig = _rig()
    obj = _radiance(view, FrameSpec("photometric", "object", azimuth_deg, POLAR), rig)
    ref = _radiance(view, FrameSpec("photometric", "reference", azimuth_deg, POLAR), rig)
    # Expected: rho·E(p')·n·l / (rho_ref·E(p)·cos θ) with p' = p - h·tanθ·u (pixel centres;
    # E is quadratic, so its box mean differs from the centre value by < 1e-6).
    c = np.arange(W) * S
    r = np.arange(H) * S
    px, py = np.meshgrid(c, r)
    h = h0 + gx * px + gy * py
    phi = np.radians(azimuth_deg)
    shift = h * np.tan(np.radians(POLAR))
    e_obj = rig.irradiance(
        "lamp", azimuth_deg, POLAR, px - shift * np.sin(phi), py - shift * np.cos(phi)
    )
    e_ref = rig.irradiance("lamp", azimuth_deg, POLAR, px, py)
    expected = (rho * e_obj * max(n @ _light(azimuth_deg), 0)) / (
        rig.reflectance_reference * e_ref * np.cos(np.radians(POLAR))
    )
    # Tolerance: each value is rounded to 1/65535 of full scale (error <= half a step), so the
    # ratio's relative error is at most q/2·(1/L_obj + 1/L_ref), plus 1e-6 for the box filter.
    q = 1.0 / CLEAN.max_value
    tol = expected * (0.5 * q / obj + 0.5 * q / ref) + 1e-6
    assert np.all(np.abs(obj / ref - expected) <= tol)


def _phase(frames: list[np.ndarray]) -> np.ndarray:
    i0, i90, i180, i270 = frames
    return np.arctan2(i270 - i90, i0 - i180)


def test_step_shifts_fringe_phase_by_minus_2pi_h_tan_over_p():
    step_um, period_um = 400.0, 2000.0
    xs = sample_coords_um(W, S, SS)[None, :]
    h = np.where(xs >= W * S / 2, step_um, 0.0) * np.ones((H * SS, 1))
    normals = np.broadcast_to(np.array([0.0, 0.0, -1.0]), (*h.shape, 3))
    view = flat_view(W, H, S, SS, height_ss_um=h, normals_ss=normals, albedo=0.45)
    rig = _rig()
    # φ = 0: fringes vary along y, the step along x, so the step casts no shadow.
    psi = {}
    for target in ("object", "reference"):
        frames = [
            _radiance(view, FrameSpec("fringe", target, 0.0, POLAR, None, period_um, ph), rig)
            for ph in (0.0, 90.0, 180.0, 270.0)
        ]
        psi[target] = _phase(frames)
    delta = np.angle(np.exp(1j * (psi["object"] - psi["reference"])))
    expected_high = -2 * np.pi * step_um * np.tan(np.radians(POLAR)) / period_um
    # Tolerance: quantisation noise q/sqrt(12) on each frame gives a phase error of about
    # sqrt(2)·q/sqrt(12)/(2·A·m) ≈ 2e-5 rad (A ≈ 0.19, m = 0.9); the pixel box weighted by a
    # non-uniform E biases the phase by < (2π s/P)²/24 · (s·|∇E|/E) ≈ 1e-4 rad. Use 1e-3.
    left, right = delta[:, : W // 2 - 1], delta[:, W // 2 + 1 :]
    assert np.max(np.abs(left)) < 1e-3
    assert np.max(np.abs(right - expected_high)) < 1e-3


def test_azimuth_zero_lights_from_plus_y():
    # h decreases toward +y: the slope faces +y (n_y > 0), so φ = 0 lights it more than φ = 180.
    view, n = _plane_view(0.0, -0.3, 0.0, 0.4)
    assert n[1] > 0
    rig = _rig()
    ratio = {}
    for az in (0.0, 90.0, 180.0):
        obj = _radiance(view, FrameSpec("photometric", "object", az, POLAR), rig)
        ref = _radiance(view, FrameSpec("photometric", "reference", az, POLAR), rig)
        ratio[az] = np.median(obj / ref)
    # Flat-fielded ratios are rho/rho_ref · n·l / cos θ: 0.807, 0.401 and 0.434 here.
    for az in ratio:
        expected = 0.4 / 0.95 * (n @ _light(az)) / np.cos(np.radians(POLAR))
        # E(p')/E(p) is not flat-fielded away: |h|·tanθ <= 960 µm and |∇E|/E <= 0.15 per
        # half field (2 mm) bound it to 1 ± 0.075.
        assert ratio[az] == pytest.approx(expected, rel=0.075)
    assert ratio[0.0] > 1.8 * ratio[180.0]


def test_shadowed_pixels_are_dark_and_lit_ones_are_not():
    block_um = 1000.0
    xs = sample_coords_um(W, S, SS)[None, :]
    ys = sample_coords_um(H, S, SS)[:, None]
    inside = (np.abs(xs - 2000) < 500) & (np.abs(ys - 1600) < 500)
    h = np.where(inside, block_um, 0.0)
    normals = np.broadcast_to(np.array([0.0, 0.0, -1.0]), (*h.shape, 3))
    view = flat_view(W, H, S, SS, height_ss_um=h, normals_ss=normals, albedo=0.5)
    # Light from +x (φ = 90°): the block (x in 15..25 px) shades x in 5..15 px (1000 µm·tan 45°).
    img = _radiance(view, FrameSpec("photometric", "object", 90.0, POLAR), _rig())
    rows = slice(13, 19)
    assert np.all(img[rows, 7:14] == 0)
    assert np.all(img[rows, 27:38] > 0.05)
    assert np.all(img[rows, 1:4] > 0.05)


def test_cast_shadow_length_matches_height_times_tan_polar():
    h = np.zeros((5, 200))
    h[:, 150:] = 300.0  # a wall at column 150, 300 µm high, samples every 10 µm
    for polar, length in ((45.0, 30), (60.0, 52)):  # 300·tanθ / 10 µm
        v = cast_shadow(h, 10.0, 90.0, polar)
        shadow = np.flatnonzero(~v[2, :150])
        # Along an axis the sweep is exact up to the sample at exactly the shadow's end.
        assert shadow.min() == pytest.approx(150 - length, abs=1)
        assert shadow.max() == 149
    assert cast_shadow(h, 10.0, 270.0, 45.0).all()  # lit from -x: the wall faces away, no cast


def test_render_frame_is_deterministic():
    view, _ = _plane_view(0.1, 0.1, 0.0, 0.4)
    noise = noise_model("default")
    frame = FrameSpec("fringe", "object", 45.0, POLAR, None, 1500.0, 90.0)
    a = render_frame(view, frame, noise, np.random.default_rng([1, 2]), rig=_rig())
    b = render_frame(view, frame, noise, np.random.default_rng([1, 2]), rig=_rig())
    c = render_frame(view, frame, noise, np.random.default_rng([1, 3]), rig=_rig())
    assert a.dtype == np.uint16 and np.array_equal(a, b) and not np.array_equal(a, c)


def test_bad_frame_specs_are_refused():
    with pytest.raises(ValueError, match="azimuth_deg"):
        FrameSpec("photometric")
    with pytest.raises(ValueError, match="channel"):
        FrameSpec("color", azimuth_deg=0.0, channel="yellow")
    with pytest.raises(ValueError, match="period_um"):
        FrameSpec("fringe", azimuth_deg=0.0, phase_deg=0.0)
    with pytest.raises(ValueError, match="polar_deg"):
        FrameSpec("photometric", azimuth_deg=0.0, polar_deg=90.0)
