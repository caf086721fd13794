"""Noise levels of the measurements, estimated from the data (inputs to the fusion weights).

- Normals: photometric stereo with K inlier lights at polar angle θ fits b = ρn by least
  squares; with shading noise σ_s (in units of n·l) the tangential error of n has variance
  ≈ σ_s²·2/(K·sin²θ) per component (LᵀL ≈ diag(K sin²θ/2, K sin²θ/2, K cos²θ)). σ_s is the
  RMS residual corrected for the 3 fitted parameters, √(K/(K−3))·residual; pixels with
  K = 3 (no residual) take the image's median. A floor of `floor_rad` stands for what the
  residual cannot see (calibration of the light directions, non-Lambertian bias).
- Fringe heights: σ_f from the data itself, 1.4826·MAD/√6 of the second differences
  h[i+1] − 2h[i] + h[i−1] along rows and columns (they cancel the surface's slope; white
  noise gives them variance 6σ²), per pixel divided by √(azimuths used / median used).
"""

from __future__ import annotations

import numpy as np

from worker.recon.arrays import fast_median

__all__ = ["NORMAL_FLOOR_RAD", "fringe_sigma_um", "normal_sigma_rad"]

# What a photometric normal's residual cannot show (light calibration, non-Lambertian bias):
# the floor of its predicted angular noise.
NORMAL_FLOOR_RAD = 0.003


def normal_sigma_rad(
    residual: np.ndarray,
    lights_used: np.ndarray,
    *,
    polar_deg: float,
    floor_rad: float = NORMAL_FLOOR_RAD,
) -> np.ndarray:
    """(H, W) float32 angular noise of photometric normals (rad); inf where not solved.

    residual: (H, W) RMS misfit in units of n·l; lights_used: (H, W) inlier count.
    """
    res = np.asarray(residual, np.float32)
    k = np.asarray(lights_used, np.float32)
    if res.shape != k.shape:
        raise ValueError(f"residual {res.shape} and lights_used {k.shape} must match")
    if not 0 < polar_deg < 90:
        raise ValueError(f"polar_deg must be in (0, 90), got {polar_deg}")
    solved = np.isfinite(res) & (k >= 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma_s = np.where(k > 3, res * np.sqrt(k / np.maximum(k - 3, 1)), np.nan)
    fit = solved & np.isfinite(sigma_s) & (k > 3)
    typical = float(fast_median(sigma_s[fit])) if fit.any() else 0.02
    sigma_s = np.where(fit, sigma_s, typical)
    sin2 = np.sin(np.radians(polar_deg)) ** 2
    sig = sigma_s * np.sqrt(2.0 / (np.maximum(k, 3) * sin2))
    sig = np.sqrt(sig**2 + floor_rad**2)
    return np.where(solved, sig, np.inf).astype(np.float32, copy=False)


def fringe_sigma_um(
    height_um: np.ndarray,
    mask: np.ndarray,
    *,
    azimuths_used: np.ndarray | None = None,
    floor_um: float = 0.05,
) -> tuple[np.ndarray, float]:
    """Per-pixel noise of the fringe heights (µm) and the image-wide estimate σ_f.

    height_um: (H, W) NaN where none; mask: (H, W) bool. Returns ((H, W) float32, inf where
    no height; σ_f).
    """
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool) & np.isfinite(h)
    if h.shape != m.shape:
        raise ValueError(f"height_um {h.shape} and mask {m.shape} must match")
    out = np.full(h.shape, np.inf, np.float32)
    if m.sum() < 25:
        return out, float("inf")
    # Second differences cancel the surface's slope; white noise gives them variance 6σ²;
    # the MAD ignores the few large values at creases and wedge rims.
    d2 = [
        (h[:, 2:] - 2 * h[:, 1:-1] + h[:, :-2])[m[:, 2:] & m[:, 1:-1] & m[:, :-2]],
        (h[2:, :] - 2 * h[1:-1, :] + h[:-2, :])[m[2:, :] & m[1:-1, :] & m[:-2, :]],
    ]
    sample = np.concatenate(d2)
    if sample.size < 25:
        return out, float("inf")
    mad = float(fast_median(np.abs(sample - fast_median(sample))))
    sigma = max(1.4826 * mad / np.sqrt(6.0), floor_um)
    if azimuths_used is not None:
        a = np.asarray(azimuths_used, np.float32)
        typical = float(fast_median(a[m])) if m.any() else 1.0
        scale = np.sqrt(typical / np.maximum(a, 1))
    else:
        scale = np.ones(h.shape, np.float32)
    out[m] = (sigma * scale)[m]
    return out, sigma


def crease_sigma_um(normals: np.ndarray, *, pixel_size_um: float) -> np.ndarray:
    """(H, W) float32 model error of a fringe height where the surface bends within a pixel.

    A fringe pixel reports (about) the height averaged over its area, not the height at its
    centre; the two differ by ≈ s²·∇²h/24 on a smooth surface and by up to s·Δg/8 at a crease
    (slope jump Δg across the pixel). With ∇²h estimated from the normals' slopes by central
    differences (a crease shows as Δg/(2s) there), s²·|∇²h|/8 bounds that error; it is added in
    quadrature to the fringe noise so that wedge rims and bottoms take their shape from the
    normals. NaN normals count as flat.
    """
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    n = np.asarray(normals, np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3), got {n.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        gx = np.nan_to_num(n[..., 0] / n[..., 2], nan=0.0, posinf=0.0, neginf=0.0)
        gy = np.nan_to_num(n[..., 1] / n[..., 2], nan=0.0, posinf=0.0, neginf=0.0)
    s = float(pixel_size_um)
    laplacian = (np.gradient(gx, axis=1) + np.gradient(gy, axis=0)) / s
    return (s * s * np.abs(laplacian) / 8.0).astype(np.float32, copy=False)
