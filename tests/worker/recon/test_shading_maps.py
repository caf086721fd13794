"""Shading maps against closed-form surfaces (sphere cap, V-groove, plane)."""

from __future__ import annotations

import numpy as np
import pytest

from worker.recon.shading_maps import (
    accessibility,
    encode_signed8,
    encode_unit8,
    mean_curvature_per_um,
    normals_rgb8,
)

S_UM = 50.0


def _cap(radius_um: float, n: int = 201) -> np.ndarray:
    """Heights of a sphere of radius R toward the camera, centred in an n×n grid."""
    c = (np.arange(n) - n // 2) * S_UM
    x, y = np.meshgrid(c, c)
    return np.sqrt(radius_um**2 - x**2 - y**2) - radius_um


def test_sphere_cap_has_mean_curvature_one_over_radius():
    radius_um = 20_000.0
    h = _cap(radius_um)
    # Central differences of step s on a sphere: relative error ~ (s/R)² · O(|∇h|²) ≈ 1e-5
    # here; Gaussian smoothing of σ = 2 px changes H by O(σ²/R²) ≈ 4e-5 relatively.
    # 1e-3 is far above both and far below a wrong factor (e.g. the ½ or the sign).
    k = mean_curvature_per_um(h, pixel_size_um=S_UM, scale_um=2 * S_UM)
    centre = k[80:121, 80:121]
    np.testing.assert_allclose(centre, 1.0 / radius_um, rtol=1e-3)
    # A trough (the cap upside down) is negative.
    k_trough = mean_curvature_per_um(-h, pixel_size_um=S_UM, scale_um=2 * S_UM)
    np.testing.assert_allclose(k_trough[80:121, 80:121], -1.0 / radius_um, rtol=1e-3)


def test_curvature_keeps_nans_and_does_not_modify_input():
    h = _cap(20_000.0, n=41)
    h[:5] = np.nan
    before = h.copy()
    k = mean_curvature_per_um(h, pixel_size_um=S_UM, scale_um=S_UM)
    assert np.isnan(k[:5]).all() and np.isfinite(k[5:]).all()
    np.testing.assert_array_equal(np.isnan(h), np.isnan(before))


def test_plane_is_fully_accessible():
    h = np.full((32, 32), 123.0)
    acc = accessibility(h, pixel_size_um=S_UM, radius_um=8 * S_UM)
    np.testing.assert_allclose(acc, 1.0)


def test_v_groove_bottom_matches_horizon_formula():
    # A groove along the rows (x direction), walls rising with slope t = tan β on both sides.
    slope = 0.5
    n = 81
    y = (np.arange(n) - n // 2) * S_UM
    h = np.repeat((slope * np.abs(y))[:, None], n, axis=1)
    acc = accessibility(h, pixel_size_um=S_UM, radius_um=10 * S_UM, n_directions=8, n_steps=10)
    # Along azimuth φ (from +x) the wall rises at t·|sin φ| per µm; the surface is piecewise
    # linear and the samples lie on one wall, so linear interpolation is exact:
    # accessibility = mean_k (1 − sin(atan(t |sin φ_k|))).
    phis = 2 * np.pi * np.arange(8) / 8
    rise = slope * np.abs(np.sin(phis))
    expected = np.mean(1 - rise / np.sqrt(1 + rise**2))
    assert acc[n // 2, n // 2] == pytest.approx(expected, abs=1e-6)
    # A point high up a wall sees the open side: more accessible than the bottom.
    assert acc[n // 2 - 20, n // 2] > acc[n // 2, n // 2]


def test_accessibility_rejects_bad_arguments():
    with pytest.raises(ValueError, match="radius_um"):
        accessibility(np.zeros((4, 4)), pixel_size_um=S_UM, radius_um=0)
    with pytest.raises(ValueError, match="height_um"):
        accessibility(np.full((4, 4), np.nan), pixel_size_um=S_UM, radius_um=S_UM)
    with pytest.raises(ValueError, match="pixel_size_um"):
        mean_curvature_per_um(np.zeros((4, 4)), pixel_size_um=-1, scale_um=1)


def test_encodings_match_the_viewer():
    # The viewer decodes k = v·255/127.5/255 … i.e. v/127.5 − 1 (frontend material.js).
    v = encode_signed8(np.array([0.0, 1e9, -1e9, np.nan]), scale=1.0)
    np.testing.assert_array_equal(v, [128, 255, 0, 128])
    np.testing.assert_array_equal(
        encode_unit8(np.array([0.0, 0.5, 1.0, np.nan])), [0, 128, 255, 255]
    )
    n = np.array([[[0.0, 0.0, -1.0], [np.nan, np.nan, np.nan]]])
    np.testing.assert_array_equal(normals_rgb8(n), [[[128, 128, 0], [128, 128, 0]]])
