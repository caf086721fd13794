"""Quality maps and noise models (worker.recon.quality)."""

import numpy as np


def _dome(rows=120, cols=160, pixel_um=100.0):
    """A dome whose sides steepen to ~75° at its foot: heights (µm) and true normals."""
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    r = np.hypot(x - cols / 2, y - rows / 2) * pixel_um
    radius = 50 * pixel_um
    h = np.where(r < radius, np.sqrt(np.clip(radius**2 - r**2, 0, None)) * 0.9, 0.0)
    gy, gx = np.gradient(h, pixel_um)
    n = np.stack([gx, gy, -np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return h.astype(np.float32), n.astype(np.float32), r < radius - pixel_um


def test_tilt_bias_measures_normals_too_steep_on_steep_ground():
    from worker.recon.quality import tilt_bias_rad

    rng = np.random.default_rng(3)
    h, n, mask = _dome()
    tilt = np.arccos(-n[..., 2])
    # Normals 4° too steep beyond 55° of tilt (attached shadows on a rim), exact elsewhere.
    extra = np.where(tilt > np.radians(55), np.radians(4.0), 0.0)
    t = np.clip(tilt + extra, 0, np.radians(89))
    az = np.arctan2(n[..., 1], n[..., 0])
    biased = np.stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), -np.cos(t)], -1)
    noisy_h = h + rng.normal(0, 2.0, h.shape).astype(np.float32)
    got = tilt_bias_rad(biased.astype(np.float32), noisy_h, mask, pixel_size_um=100.0)
    steep = mask & (tilt > np.radians(60)) & (tilt < np.radians(70))
    flat = mask & (tilt < np.radians(25))
    assert abs(np.median(got[steep]) - np.radians(4.0)) < np.radians(1.0)
    assert np.median(got[flat]) < np.radians(0.3)
    # Unbiased normals: nothing beyond the slope noise of the heights.
    none = tilt_bias_rad(n, noisy_h, mask, pixel_size_um=100.0)
    assert np.percentile(none[mask], 95) < np.radians(0.5)
