"""Simultaneous registration of all scans by projective point-to-plane correspondences.

Each scan is a height map seen along its own view axis, so the surface point of scan ``b``
that a point ``x`` of scan ``a`` should lie on is found by projecting ``x`` into ``b``'s image
and interpolating ``b``'s heights and normals there (projective data association: Blais &
Levine 1995; simultaneous registration of range images by Gauss–Newton over all poses at
once: Neugebauer 1997, "Reconstruction of real-world objects via simultaneous registration
and robust combination of multiple range images"). Unlike nearest-neighbour ICP this pairs a
point with the *interpolated surface*, not with whichever sample happens to be closest: on the
narrow, steep overlap bands at a tablet's rims the samples of two scans are up to a pixel or
two apart in 3-D, and nearest-sample pairing within a small radius selects a biased subset,
while a large radius pairs points beside the overlap. A point is used only where ``b`` has
valid samples on all four corners of the interpolation cell and where ``b`` would see it (its
normal faces ``b``'s camera), so the overlap's extent is ``b``'s own coverage.

Residual of a correspondence (tablet frame): r = m·(x − y), x = T_a·p, y = T_b·s_b(p),
m = R_b·n_b; for small motions x → x + ω×x + t of every scan (left-multiplied updates),
∂r/∂(ω_a, t_a) = (x × m, m) and ∂r/∂(ω_b, t_b) = (m × (x − y) − y × m, −m).
Weights: Tukey's biweight on r with the scale from the median absolute residual (robust to
wedge walls and mixed pixels), times the inverse variance of a height sample along the
normal, σ² ∝ 1 + tan²θ for view tilt θ (a pixel's height on a slope averages a stretch of
depth s·tanθ long, so its error grows with the slope, SCAN_BUNDLE.md's pixel model).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from worker.register.o3d import rigid
from worker.register.pointcloud import ScanCloud

__all__ = ["joint_refine", "projective_pairs", "silhouette_consistency"]


def _bilinear(grid_values: np.ndarray, valid: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """Bilinear interpolation of (H, W[, k]) values at fractional (rows, cols); returns the
    values and a mask of the points whose four corners are all valid."""
    h, w = valid.shape
    r0 = np.floor(rows).astype(np.int64)
    c0 = np.floor(cols).astype(np.int64)
    inside = (r0 >= 0) & (c0 >= 0) & (r0 < h - 1) & (c0 < w - 1)
    r0 = np.where(inside, r0, 0)
    c0 = np.where(inside, c0, 0)
    ok = inside & valid[r0, c0] & valid[r0 + 1, c0] & valid[r0, c0 + 1] & valid[r0 + 1, c0 + 1]
    fr = rows - r0
    fc = cols - c0
    if grid_values.ndim == 3:
        fr = fr[:, None]
        fc = fc[:, None]
    v = (
        grid_values[r0, c0] * (1 - fr) * (1 - fc)
        + grid_values[r0 + 1, c0] * fr * (1 - fc)
        + grid_values[r0, c0 + 1] * (1 - fr) * fc
        + grid_values[r0 + 1, c0 + 1] * fr * fc
    )
    return v, ok


def projective_pairs(
    a: ScanCloud,
    b: ScanCloud,
    t_a: np.ndarray,
    t_b: np.ndarray,
    *,
    gate_mm: float,
    max_tilt_deg: float = 70.0,
    max_normal_angle_deg: float = 30.0,
    stride: int = 1,
):
    """Correspondences of ``a``'s points on ``b``'s surface (both placed by their 4×4
    scan → tablet transforms). Returns (x, y, m, tilt_cos_a, tilt_cos_b) in the tablet frame:
    points of ``a``, their surface points on ``b``, ``b``'s unit normals there, and the cosines
    of each sample's view tilt (|n_z| in its own scan frame). A pair is kept when ``b`` has
    valid samples around the projection, ``a``'s normal faces ``b``'s camera within
    ``max_tilt_deg``, the two normals agree within ``max_normal_angle_deg`` and the distance
    along ``b``'s normal is under ``gate_mm``."""
    x, y, m, ca, cb, _ = _projective(
        a, b, t_a, t_b, gate_mm, max_tilt_deg, max_normal_angle_deg, stride
    )
    return x, y, m, ca, cb


def _projective(a, b, t_a, t_b, gate_mm, max_tilt_deg, max_normal_angle_deg, stride=1):
    if b.grid is None:
        raise ValueError(f"{b.label}: no height map (grid) to project onto")
    p = a.points_mm[::stride]
    na = a.normals[::stride]
    rel = np.linalg.inv(t_b) @ t_a
    q = p @ rel[:3, :3].T + rel[:3, 3]  # a's points in b's scan frame
    nq = na @ rel[:3, :3].T
    facing = nq[:, 2] < -np.cos(np.radians(max_tilt_deg))
    s_mm = b.pixel_size_um / 1000.0
    rows = q[:, 1] / s_mm
    cols = q[:, 0] / s_mm
    h_um, ok = _bilinear(b.grid.height_um, b.grid.valid, rows, cols)
    n_b, _ = _bilinear(b.grid.normals, b.grid.valid, rows, cols)
    ok &= facing
    q, nq, h_um, n_b, na = q[ok], nq[ok], h_um[ok], n_b[ok], na[ok]
    n_b = n_b / np.linalg.norm(n_b, axis=1, keepdims=True)
    y = np.stack([q[:, 0], q[:, 1], -h_um / 1000.0], axis=1)
    dist = np.einsum("ij,ij->i", q - y, n_b)
    agree = np.einsum("ij,ij->i", nq, n_b) > np.cos(np.radians(max_normal_angle_deg))
    keep = agree & (np.abs(dist) < gate_mm)
    q, y, n_b, na, nq, dist = q[keep], y[keep], n_b[keep], na[keep], nq[keep], dist[keep]
    rb = t_b[:3, :3]
    x_t = q @ rb.T + t_b[:3, 3]
    y_t = y @ rb.T + t_b[:3, 3]
    m_t = n_b @ rb.T
    return x_t, y_t, m_t, np.abs(na[:, 2]), np.abs(n_b[:, 2]), dist


def silhouette_consistency(
    scans: list[ScanCloud], transforms: list, k: int, *, tolerance_px: float, stride: int = 4
) -> float:
    """Of the points of the other placed scans (``transforms``; None = not placed) projected
    into scan ``k``'s image, and of ``k``'s points projected into each other scan's image,
    the fraction that falls within ``tolerance_px`` of that image's tablet mask and not more
    than ``tolerance_px`` (pixel sizes) in front of that image's measured surface.

    Every view is orthographic and sees the whole tablet's outline, so every surface point
    of the tablet lies inside every view's silhouette (the visual hull; silhouette
    coherence, Hernández, Schmitt & Cipolla 2007). A pose that slides a rounded edge scan
    around the tablet, which point-to-surface distances hardly notice, swings that view's
    silhouette across the others' points. The hull alone accepts a face tilted into the
    tablet's interior (issue 8: the reverse tilted 16.8°, every point inside every
    silhouette); a view, though, sees the nearest surface, so no point of the tablet lies in
    front of it (free-space / visibility consistency, Merrell et al., "Real-time
    visibility-based fusion of depth maps", ICCV 2007), and the sunken face's own view has
    the edges' points millimetres in front of it. 1.0 for a consistent pose."""
    inside = total = 0
    for j, t in enumerate(transforms):
        if j == k or t is None:
            continue
        for a, b, ta, tb in ((j, k, t, transforms[k]), (k, j, transforms[k], t)):
            grid = scans[b].grid
            if grid is None or grid.outside_px is None:
                continue
            rel = np.linalg.inv(tb) @ ta
            q = scans[a].points_mm[::stride] @ rel[:3, :3].T + rel[:3, 3]
            s_mm = scans[b].pixel_size_um / 1000.0
            r = np.rint(q[:, 1] / s_mm).astype(np.int64)
            c = np.rint(q[:, 0] / s_mm).astype(np.int64)
            h, w = grid.outside_px.shape
            # Beyond the image's border: as the border pixel there, so that a tablet cut by
            # the frame is not held against the scan, and a scan thrown far off counts.
            rc, cc = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
            d = grid.outside_px[rc, cc]
            # View z = −h: a point nearer the camera than the measured surface (pixels where
            # the height is kept only; elsewhere, as off the image, nothing is known).
            surface_z_mm = -grid.height_um[rc, cc] / 1000.0
            ahead_px = np.nan_to_num((surface_z_mm - q[:, 2]) / s_mm, nan=-np.inf)
            ahead_px[(r != rc) | (c != cc)] = -np.inf
            total += len(d)
            inside += int(np.sum((d <= tolerance_px) & (ahead_px <= tolerance_px)))
    return inside / total if total else 1.0


def _tukey(r: np.ndarray, c: float) -> np.ndarray:
    u = r / c
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)


def joint_refine(
    scans: list[ScanCloud],
    transforms: list[np.ndarray],
    *,
    anchor: int,
    gates_mm: tuple[float, ...],
    iterations: int = 8,
    min_pairs: int = 30,
    floor_sigma_mm: float = 0.001,
    max_tilt_deg: float = 70.0,
) -> tuple[list[np.ndarray], dict[tuple[str, str], tuple[int, float]]]:
    """Gauss–Newton over all scan poses at once (``anchor`` fixed) on the projective
    point-to-plane residuals of every ordered pair of scans; up to ``iterations`` steps at
    each correspondence gate of ``gates_mm`` (coarse to fine). Returns the transforms and,
    per ordered pair (labels) with at least ``min_pairs`` correspondences at the last step,
    their number and RMS point-to-surface distance (µm) among the inliers."""
    n = len(scans)
    out = [np.array(t, dtype=np.float64) for t in transforms]
    free = [k for k in range(n) if k != anchor]
    col = {k: 6 * i for i, k in enumerate(free)}
    stats: dict[tuple[str, str], tuple[int, float]] = {}
    # farthest point of each scan from the tablet frame's origin (the lever of a rotation)
    radius = {
        k: float(np.linalg.norm(s.points_mm @ out[k][:3, :3].T + out[k][:3, 3], axis=1).max())
        for k, s in enumerate(scans)
    }
    for gate in gates_mm:
        for _ in range(iterations):
            pairs = []
            for ia in range(n):
                for ib in range(n):
                    if ia == ib:
                        continue
                    pr = projective_pairs(
                        scans[ia],
                        scans[ib],
                        out[ia],
                        out[ib],
                        gate_mm=gate,
                        max_tilt_deg=max_tilt_deg,
                    )
                    if len(pr[0]) >= min_pairs:
                        pairs.append((ia, ib, *pr))
            if not pairs:
                return out, stats
            res = [np.einsum("ij,ij->i", x - y, m) for _, _, x, y, m, _, _ in pairs]
            sigma = max(1.4826 * float(np.median(np.abs(np.concatenate(res)))), floor_sigma_mm)
            h = np.zeros((6 * len(free), 6 * len(free)))
            g = np.zeros(6 * len(free))
            stats = {}
            for r, (ia, ib, x, y, m, ca, cb) in zip(res, pairs, strict=True):
                # A pixel's height on a slope averages a stretch of depth s·tanθ: the variance
                # of each sample along the normal grows as 1/cos²θ of its own view's tilt.
                w = _tukey(r, 4.685 * sigma) / (1.0 / ca**2 + 1.0 / cb**2)
                ja = np.concatenate([np.cross(x, m), m], axis=1)
                jb = np.concatenate([np.cross(m, x - y) - np.cross(y, m), -m], axis=1)
                blocks = [(col[k], j) for k, j in ((ia, ja), (ib, jb)) if k in col]
                for c1, j1 in blocks:
                    g[c1 : c1 + 6] += j1.T @ (w * r)
                    for c2, j2 in blocks:
                        h[c1 : c1 + 6, c2 : c2 + 6] += (j1 * w[:, None]).T @ j2
                inl = w > 0
                if inl.any():
                    rms = float(np.sqrt(np.mean(r[inl] ** 2)) * 1000.0)
                    stats[(scans[ia].label, scans[ib].label)] = (int(inl.sum()), rms)
            # Levenberg–Marquardt's tiny damping only guards an unconstrained direction
            # (a scan without overlap); the robust weights do the rest.
            damp = 1e-6 * np.trace(h) / len(h) + 1e-12
            delta = -np.linalg.solve(h + damp * np.eye(len(h)), g)
            # No scan's points may move farther than the gate in one step: beyond it the
            # linearisation and the correspondences no longer hold.
            reach = max(
                float(np.linalg.norm(delta[c + 3 : c + 6]))
                + float(np.linalg.norm(delta[c : c + 3])) * radius[k]
                for k, c in col.items()
            )
            if reach > gate:
                delta *= gate / reach
            for k, c in col.items():
                rot = Rotation.from_rotvec(delta[c : c + 3]).as_matrix()
                out[k] = rigid(rot, delta[c + 3 : c + 6]) @ out[k]
            if np.abs(delta).max() < 1e-7:
                break
    return out, stats
