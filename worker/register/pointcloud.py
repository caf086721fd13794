"""A reconstructed scan as an oriented, coloured point cloud in its own scan frame (mm).

The scan frame is SCAN_BUNDLE.md's: the centre of pixel (r, c) images (c·s, r·s) µm, the
surface point seen there is (c·s, r·s, −h) µm, unit normals face the camera (n_z < 0) and
so point out of the tablet. Points are given in millimetres, the unit of ``mesh.ply``.

Pixels within ``erode_px`` of the mask's rim are dropped: there the surface is seen at a
grazing angle and both heights and normals are least reliable (SCAN_BUNDLE.md's mesh keeps
them; registration and fusion should not trust them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["ScanCloud", "ScanGrid", "scan_cloud"]


@dataclass(frozen=True, eq=False)
class ScanCloud:
    """One scan's surface samples in its scan frame.

    points_mm: (N, 3) float64; normals: (N, 3) unit, outward; colours: (N, 3) float64 in
    [0, 1] (sRGB as stored in albedo.png); pixel_size_um: lateral sampling; label: the scan's
    name in reports (face or id); face: scan.face; pose: (3, 3) rotation tablet → scan or None;
    grid: the height map the points came from (None for a bare point cloud).
    """

    points_mm: np.ndarray
    normals: np.ndarray
    colours: np.ndarray
    pixel_size_um: float
    label: str
    face: str = "other"
    pose: np.ndarray | None = None
    grid: ScanGrid | None = None


@dataclass(frozen=True, eq=False)
class ScanGrid:
    """The scan's height map as a surface that can be sampled anywhere (projective
    correspondences, :mod:`worker.register.joint`): height_um (H, W), normals (H, W, 3) and
    ``valid`` (H, W) bool, the pixels kept as points (finite, eroded mask, not too steep);
    outside_px (H, W): each pixel's distance (pixels) to the mask, 0 on it (the silhouette)."""

    height_um: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    outside_px: np.ndarray | None = None


def scan_cloud(
    height_um: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    albedo_rgb8: np.ndarray | None,
    *,
    pixel_size_um: float,
    label: str,
    face: str = "other",
    pose: np.ndarray | None = None,
    erode_px: int = 2,
    max_tilt_deg: float = 70.0,
) -> ScanCloud:
    """The model directory's arrays as a :class:`ScanCloud`.

    height_um (H, W) µm with NaN off the surface; normals (H, W, 3); mask (H, W) bool;
    albedo_rgb8 (H, W, 3) uint8 or None (grey). A pixel is kept when it is in the mask eroded
    by ``erode_px``, its height and normal are finite and its normal is within ``max_tilt_deg``
    of the view axis.
    """
    h = np.asarray(height_um, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"height_um must be (H, W), got shape {h.shape}")
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != (*h.shape, 3):
        raise ValueError(f"normals must have shape {(*h.shape, 3)}, got {n.shape}")
    m = np.asarray(mask, dtype=bool)
    if m.shape != h.shape:
        raise ValueError(f"mask must have shape {h.shape}, got {m.shape}")
    if not (np.isfinite(pixel_size_um) and pixel_size_um > 0):
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um!r}")
    if erode_px < 0:
        raise ValueError(f"erode_px must be >= 0, got {erode_px}")
    if pose is not None:
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (3, 3) or not np.allclose(pose @ pose.T, np.eye(3), atol=1e-4):
            raise ValueError(f"pose of {label}: must be a 3×3 rotation matrix")
    keep = ndimage.binary_erosion(m, iterations=erode_px) if erode_px else m.copy()
    keep &= np.isfinite(h) & np.all(np.isfinite(n), axis=-1)
    # A pixel whose surface is steeply tilted averages a long stretch of depth: its height is
    # a blend, not a surface point; the neighbouring scan sees that stretch face on.
    keep &= np.nan_to_num(n[..., 2], nan=0.0) < -np.cos(np.radians(max_tilt_deg))
    if keep.sum() < 100:
        raise ValueError(f"{label}: fewer than 100 usable surface pixels")
    rows, cols = np.nonzero(keep)
    s_mm = pixel_size_um / 1000.0
    points = np.stack([cols * s_mm, rows * s_mm, -h[rows, cols] / 1000.0], axis=-1)
    nn = n[rows, cols]
    nn = nn / np.linalg.norm(nn, axis=-1, keepdims=True)
    if albedo_rgb8 is None:
        colours = np.full((len(rows), 3), 0.6)
    else:
        a = np.asarray(albedo_rgb8)
        if a.shape[:2] != h.shape:
            raise ValueError(f"albedo must have shape {h.shape}[+3], got {a.shape}")
        a = a[rows, cols]
        colours = (np.repeat(a[:, None], 3, 1) if a.ndim == 1 else a[:, :3]) / 255.0
    grid = ScanGrid(
        np.where(keep, h, np.nan),
        np.where(keep[..., None], n, np.nan),
        keep,
        ndimage.distance_transform_edt(~m).astype(np.float32),
    )
    return ScanCloud(
        points, nn, colours.astype(np.float64), float(pixel_size_um), label, face, pose, grid
    )
