"""Seams blended where the faces of a whole tablet overlap.

Each face keeps its own image grid (its GLB node maps it into the tablet frame); where other
faces saw the same stretch of surface, its normals and albedo become the weighted mean of
every face that saw it, with each face's quality weight w (`face_weight`). The weights are a
partition of unity over the faces that see a point, so two overlapping faces hold the same
blended value wherever they overlap: wherever the viewer changes from one face to the other,
nothing changes on screen (no seam), and far from the other faces each face keeps its own
measurement. The blend of several range scans by confidence weights is Curless & Levoy's
("A volumetric method for building complex models from range images", SIGGRAPH 1996), here on
each face's grid instead of a volume.

A point of face A counts as seen by face B only where B's own height there agrees with the
point (within ``tolerance_um``): B saw that surface and not another one in front of or behind
it (the reverse lies "under" the obverse on B's grid), so no face lends its relief to a
surface it did not see (no double relief).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt, map_coordinates

__all__ = ["FaceGrid", "blend_faces", "face_weight"]


def face_weight(
    normals: np.ndarray, mask: np.ndarray, *, pixel_size_um: float, feather_mm: float = 0.5
) -> np.ndarray:
    """(H, W) float in [0, 1]: a face's quality weight where faces of the whole tablet overlap.

    w = min(1, d / feather) · cos²θ: d is the Euclidean distance (px) to the nearest pixel off
    the mask (pixels at the rim mix tablet and background), θ the normal's tilt from the view
    axis (−z); cos²θ because a height sample's variance along the normal grows as 1/cos²θ
    (the weighting of `worker.register.joint`), so the face that saw a stretch more squarely
    measured it better. 0 off the mask.
    """
    n = np.asarray(normals, np.float64)
    m = np.asarray(mask, bool)
    if n.ndim != 3 or n.shape[2] != 3 or n.shape[:2] != m.shape:
        raise ValueError(f"normals must be (H, W, 3) and mask (H, W); got {n.shape}, {m.shape}")
    if not pixel_size_um > 0 or not feather_mm > 0:
        raise ValueError("pixel_size_um and feather_mm must be > 0")
    ok = m & np.all(np.isfinite(n), axis=2)
    feather_px = max(2.0, feather_mm * 1000.0 / pixel_size_um)
    dist_px = distance_transform_edt(np.pad(ok, 1))[1:-1, 1:-1]
    cos_tilt = np.clip(-np.nan_to_num(n[..., 2]), 0.0, 1.0)
    return np.where(ok, np.minimum(1.0, dist_px / feather_px) * cos_tilt**2, 0.0)


@dataclass(frozen=True)
class FaceGrid:
    """One face on its image grid, scan frame (SCAN_BUNDLE.md): height (H, W) µm, unit
    normals (H, W, 3), mask (H, W), albedo (H, W, 3) float (any linear or encoded scale, the
    same for every face) or None, pixel size µm, and ``transform`` 4×4 scan → tablet (mm)."""

    height_um: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray | None
    pixel_size_um: float
    transform: np.ndarray


def _sample(grid: np.ndarray, rows: np.ndarray, cols: np.ndarray, order: int) -> np.ndarray:
    """Values of ``grid`` (H, W[, C]) at fractional (rows, cols): bilinear (order 1) or the
    nearest pixel (order 0)."""
    coords = np.stack([rows, cols])
    if grid.ndim == 2:
        return map_coordinates(grid, coords, order=order, mode="nearest")
    return np.stack(
        [map_coordinates(grid[..., k], coords, order=order, mode="nearest") for k in range(3)],
        axis=-1,
    )


def blend_faces(
    faces: list[FaceGrid], *, weights: list[np.ndarray] | None = None, tolerance_um: float = 0.0
) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Per face, (normals (H, W, 3), albedo (H, W, 3) or None) blended with the other faces.

    At a pixel p of face A (in its mask), with X_A(p) its point in the tablet frame, the
    faces B that saw X_A(p) (inside B's grid, in B's mask, B's height there within
    ``tolerance_um`` of X_A(p)'s; default max(100 µm, 4 pixels of B)) give
    n(p) = normalise(Σ w_B · R_Aᵀ R_B n_B) and a(p) = Σ w_B a_B / Σ w_B over A and those B,
    sampled bilinearly on B's grid. ``weights``: each face's w (default `face_weight`).
    Where Σ w = 0 (A's rim with nobody else) the face keeps its own values.
    """
    if weights is None:
        weights = [face_weight(f.normals, f.mask, pixel_size_um=f.pixel_size_um) for f in faces]
    if len(weights) != len(faces):
        raise ValueError("weights: one per face")
    clean = []
    for f, w in zip(faces, weights, strict=True):
        if f.height_um.shape != f.mask.shape or f.normals.shape != (*f.mask.shape, 3):
            raise ValueError("each face's height, normals and mask must share one (H, W) grid")
        if np.asarray(w).shape != f.mask.shape:
            raise ValueError("each face's weight must be (H, W) like its mask")
        ok = np.asarray(f.mask, bool) & np.isfinite(f.height_um)
        ok &= np.all(np.isfinite(f.normals), axis=2)
        clean.append(
            (
                ok,
                np.where(ok, f.height_um, np.nan),
                np.where(ok[..., None], f.normals, 0.0),
                np.where(ok, np.asarray(w, np.float64), 0.0),
                None if f.albedo is None else np.where(ok[..., None], f.albedo, 0.0),
            )
        )
    with_albedo = all(f.albedo is not None for f in faces)
    out = []
    for a, face_a in enumerate(faces):
        ok_a, h_a, n_a, w_a, alb_a = clean[a]
        rows, cols = np.nonzero(ok_a)
        s_a = face_a.pixel_size_um
        p_a = np.stack([cols * s_a, rows * s_a, -h_a[rows, cols]], axis=1) / 1000.0  # mm
        acc_n = w_a[rows, cols, None] * n_a[rows, cols]
        acc_w = w_a[rows, cols].copy()
        acc_alb = None if not with_albedo else w_a[rows, cols, None] * alb_a[rows, cols]
        for b, face_b in enumerate(faces):
            if b == a:
                continue
            ok_b, h_b, n_b, w_b, alb_b = clean[b]
            m = np.linalg.inv(face_b.transform) @ face_a.transform  # A's scan → B's scan
            p_b = p_a @ m[:3, :3].T + m[:3, 3]
            s_b = face_b.pixel_size_um
            r_b, c_b = p_b[:, 1] * 1000.0 / s_b, p_b[:, 0] * 1000.0 / s_b
            hgt, wid = ok_b.shape
            inside = (r_b >= 0) & (r_b <= hgt - 1) & (c_b >= 0) & (c_b <= wid - 1)
            if not inside.any():
                continue
            idx = np.nonzero(inside)[0]
            r, c = r_b[idx], c_b[idx]
            near_ok = _sample(ok_b.astype(np.float64), r, c, 0) > 0.5
            near_h = _sample(np.nan_to_num(h_b), r, c, 0)
            tol = tolerance_um or max(100.0, 4.0 * s_b)
            seen = near_ok & (np.abs(near_h - (-p_b[idx, 2] * 1000.0)) <= tol)
            idx, r, c = idx[seen], r[seen], c[seen]
            if len(idx) == 0:
                continue
            w = _sample(w_b, r, c, 1)
            normal_b = _sample(n_b, r, c, 1) @ m[:3, :3]  # B's scan frame → A's: Mᵀ n
            acc_n[idx] += w[:, None] * normal_b
            acc_w[idx] += w
            if acc_alb is not None:
                acc_alb[idx] += w[:, None] * _sample(alb_b, r, c, 1)
        normals = np.array(face_a.normals, np.float64, copy=True)
        albedo = None if face_a.albedo is None else np.array(face_a.albedo, np.float64, copy=True)
        any_w = acc_w > 0
        length = np.linalg.norm(acc_n, axis=1)
        use = any_w & (length > 0)
        normals[rows[use], cols[use]] = acc_n[use] / length[use, None]
        if albedo is not None and acc_alb is not None:
            albedo[rows[any_w], cols[any_w]] = acc_alb[any_w] / acc_w[any_w, None]
        out.append((normals, albedo))
    return out
