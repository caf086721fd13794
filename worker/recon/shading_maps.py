"""Shading maps for the viewer, on the image grid: mean curvature, accessibility, normals.

Pure functions on arrays (no I/O). Heights follow SCAN_BUNDLE.md: h in µm toward the camera,
pixel (r, c) at (c·s, r·s) µm; NaN outside the reconstructed surface.

- :func:`mean_curvature_per_um`: H = ½ ∇·(∇h / √(1 + |∇h|²)) of the surface z = h(x, y)
  (do Carmo, *Differential Geometry of Curves and Surfaces*, §3-3), after Gaussian smoothing
  of h with σ = ``scale_um`` so that each map shows the relief at one scale. H > 0 where the
  surface is convex toward the camera (a ridge), H < 0 in a wedge's trough.
- :func:`accessibility`: horizon-based ambient occlusion (Bavoil, Sainz & Dimitrov,
  "Image-space horizon-based ambient occlusion", SIGGRAPH 2008 talk): for each of
  ``n_directions`` azimuths the elevation α of the highest horizon within ``radius_um``;
  accessibility = mean over directions of 1 − sin α (1 = open flat surface, 0 = enclosed).
- :func:`encode_signed8`, :func:`encode_unit8`, :func:`normals_rgb8`: 8-bit encodings the
  viewer reads (signed: grey 128 = 0, k = v/127.5 − 1; unit: 0…255; normals RGB = (n+1)/2).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = [
    "accessibility",
    "encode_signed8",
    "encode_unit8",
    "mean_curvature_per_um",
    "normals_rgb8",
    "robust_scale",
]


def _check_height(height_um: np.ndarray, pixel_size_um: float) -> np.ndarray:
    h = np.asarray(height_um)
    if h.ndim != 2 or min(h.shape) < 2:
        raise ValueError(f"height_um must be a 2-D array of at least 2×2, got shape {h.shape}")
    if not (np.isfinite(pixel_size_um) and pixel_size_um > 0):
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um!r}")
    return h.astype(np.float64)


def _filled(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h with NaNs replaced by the nearest finite value (so smoothing and slopes do not see
    cliffs at the rim), and the mask of finite values."""
    finite = np.isfinite(h)
    if not finite.any():
        raise ValueError("height_um has no finite value")
    if finite.all():
        return h, finite
    idx = ndimage.distance_transform_edt(~finite, return_distances=False, return_indices=True)
    return h[tuple(idx)], finite


def mean_curvature_per_um(
    height_um: np.ndarray, *, pixel_size_um: float, scale_um: float
) -> np.ndarray:
    """Mean curvature H (1/µm), (H, W) float32, of h smoothed with a Gaussian of σ = scale_um.

    NaN where h is NaN. A sphere cap of radius R toward the camera gives H = 1/R.
    """
    h = _check_height(height_um, pixel_size_um)
    if not (np.isfinite(scale_um) and scale_um >= 0):
        raise ValueError(f"scale_um must be >= 0, got {scale_um!r}")
    filled, finite = _filled(h)
    sigma_px = scale_um / pixel_size_um
    smooth = ndimage.gaussian_filter(filled, sigma_px, mode="nearest") if sigma_px > 0 else filled
    gy, gx = np.gradient(smooth, pixel_size_um)
    norm = np.sqrt(1.0 + gx * gx + gy * gy)
    div = np.gradient(gx / norm, pixel_size_um, axis=1) + np.gradient(
        gy / norm, pixel_size_um, axis=0
    )
    # z = h is toward the camera, so div(∇h/|·|) < 0 on a cap: H = -½ div is > 0 on ridges.
    curvature = -0.5 * div
    return np.where(finite, curvature, np.nan).astype(np.float32)


def accessibility(
    height_um: np.ndarray,
    *,
    pixel_size_um: float,
    radius_um: float,
    n_directions: int = 8,
    n_steps: int = 8,
) -> np.ndarray:
    """Accessibility in [0, 1], (H, W) float32, NaN where h is NaN (horizon-based AO).

    The horizon is sampled at ``n_steps`` distances up to ``radius_um`` (at least one
    pixel apart) along ``n_directions`` azimuths; off-surface samples do not occlude.
    """
    h = _check_height(height_um, pixel_size_um)
    if not (np.isfinite(radius_um) and radius_um > 0):
        raise ValueError(f"radius_um must be > 0, got {radius_um!r}")
    if n_directions < 1 or n_steps < 1:
        raise ValueError("n_directions and n_steps must be >= 1")
    finite = np.isfinite(h)
    if not finite.any():
        raise ValueError("height_um has no finite value")
    low = np.nanmin(h) - 1.0  # off-surface samples sit below everything: no occlusion
    base = np.where(finite, h, low)
    radius_px = radius_um / pixel_size_um
    distances_px = np.unique(np.maximum(1.0, np.linspace(0, radius_px, n_steps + 1)[1:]))
    rows, cols = np.indices(h.shape, dtype=np.float64)
    total = np.zeros(h.shape)
    for k in range(n_directions):
        phi = 2 * np.pi * k / n_directions
        dr, dc = np.sin(phi), np.cos(phi)
        tan_max = np.zeros(h.shape)  # a flat neighbourhood: horizon at 0 rad
        for d in distances_px:
            sample = ndimage.map_coordinates(
                base, [rows + d * dr, cols + d * dc], order=1, mode="nearest"
            )
            tan_max = np.maximum(tan_max, (sample - base) / (d * pixel_size_um))
        total += 1.0 - tan_max / np.sqrt(1.0 + tan_max * tan_max)  # 1 - sin(atan(t))
    out = total / n_directions
    return np.where(finite, out, np.nan).astype(np.float32)


def robust_scale(values: np.ndarray, *, percentile: float = 98.0) -> float:
    """The ``percentile`` of |values| over finite entries (a display range); 1 if none."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 1.0
    scale = float(np.percentile(v, percentile))
    return scale if scale > 0 else 1.0


def encode_signed8(values: np.ndarray, *, scale: float) -> np.ndarray:
    """uint8 grey: 128 + 127·tanh(v/scale) rounded (128 = 0); NaN → 128."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be > 0, got {scale!r}")
    v = np.asarray(values, dtype=np.float64)
    k = np.tanh(np.where(np.isfinite(v), v, 0.0) / scale)
    return np.clip(np.rint(127.5 * (k + 1.0)), 0, 255).astype(np.uint8)


def encode_unit8(values: np.ndarray, *, fill: float = 1.0) -> np.ndarray:
    """uint8 grey: 255·clip(v, 0, 1) rounded; NaN → ``fill``."""
    v = np.asarray(values, dtype=np.float64)
    v = np.clip(np.where(np.isfinite(v), v, fill), 0.0, 1.0)
    return np.rint(255.0 * v).astype(np.uint8)


def normals_rgb8(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB = round(255·(n + 1)/2); NaN → the camera-facing (0, 0, −1)."""
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim != 3 or n.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {n.shape}")
    ok = np.all(np.isfinite(n), axis=-1, keepdims=True)
    n = np.where(ok, n, np.array([0.0, 0.0, -1.0]))
    return np.clip(np.rint(127.5 * (n + 1.0)), 0, 255).astype(np.uint8)
