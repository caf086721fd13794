"""Any triangle mesh (PLY/OBJ/STL via trimesh) as the scanned object: a numpy z-buffer.

The mesh is taken in the tablet frame of ``tablet.py`` (obverse toward -z) in mm, centred
on its bounding-box centre. Every sample of the supersampled grid takes the nearest
triangle covering it (orthographic along +z); height comes from the triangle's plane and
the normal is the triangle's own (flat) normal, so ground-truth normals are exactly the
derivative of the ground-truth heights. Colours: the mesh's vertex colours (sRGB,
interpolated, linearised) or a uniform clay colour.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from worker.simulate.view import View, assemble_view, sample_coords_um

__all__ = ["MeshTablet", "load_mesh", "mesh_points", "render_mesh_view"]

CLAY_RGB = (0.46, 0.34, 0.23)
_CHUNK = 2_000_000  # candidate samples per vectorised batch


@dataclass(frozen=True)
class MeshTablet:
    """vertices_um (V, 3) centred, faces (F, 3), optional linear RGB per vertex (V, 3)."""

    vertices_um: np.ndarray
    faces: np.ndarray
    vertex_rgb: np.ndarray | None


def load_mesh(path: str | Path) -> MeshTablet:
    """Read a mesh file (units: mm) with trimesh; ValueError naming the file if unusable."""
    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for bad files
        raise ValueError(f"mesh: cannot read {path}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"mesh: {path} holds no triangles")
    verts = np.asarray(mesh.vertices, float) * 1000.0
    verts -= 0.5 * (verts.min(axis=0) + verts.max(axis=0))
    rgb = None
    colors = getattr(mesh.visual, "vertex_colors", None)
    if mesh.visual.kind == "vertex" and colors is not None and len(colors) == len(verts):
        srgb = np.asarray(colors, float)[:, :3] / 255.0
        rgb = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return MeshTablet(verts, np.asarray(mesh.faces, np.int64), rgb)


def _rasterise(tri: np.ndarray, xs: np.ndarray, ys: np.ndarray, step: float):
    """Nearest triangle per sample: depth (Hs, Ws) (inf: none), triangle id, barycentrics."""
    hs, ws = len(ys), len(xs)
    depth = np.full(hs * ws, np.inf)
    tri_id = np.full(hs * ws, -1)
    bary = np.zeros((hs * ws, 3))
    x0, y0 = xs[0], ys[0]
    lo = np.floor((tri[:, :, :2].min(axis=1) - (x0, y0)) / step).astype(int)
    hi = np.ceil((tri[:, :, :2].max(axis=1) - (x0, y0)) / step).astype(int)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, (ws - 1, hs - 1))
    span = np.max(hi - lo + 1, axis=1)
    valid = np.all(hi >= lo, axis=1)
    for size in np.unique(span[valid]):
        for ids in np.array_split(
            np.flatnonzero(valid & (span == size)),
            max(1, int(np.sum(valid & (span == size))) * size * size // _CHUNK),
        ):
            if ids.size == 0:
                continue
            off = np.arange(size)
            cx = (lo[ids, 0][:, None, None] + off[None, None, :]).repeat(size, 1)
            cy = (lo[ids, 1][:, None, None] + off[None, :, None]).repeat(size, 2)
            px, py = x0 + cx * step, y0 + cy * step
            a, b, c = (tri[ids, k][:, None, None, :] for k in range(3))
            det = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (c[..., 0] - a[..., 0]) * (
                b[..., 1] - a[..., 1]
            )
            with np.errstate(divide="ignore", invalid="ignore"):
                l1 = (
                    (px - a[..., 0]) * (c[..., 1] - a[..., 1])
                    - (c[..., 0] - a[..., 0]) * (py - a[..., 1])
                ) / det
                l2 = (
                    (b[..., 0] - a[..., 0]) * (py - a[..., 1])
                    - (px - a[..., 0]) * (b[..., 1] - a[..., 1])
                ) / det
                l0 = 1 - l1 - l2
            inside = (
                (l0 >= 0)
                & (l1 >= 0)
                & (l2 >= 0)
                & (cx <= hi[ids, 0][:, None, None])
                & (cy <= hi[ids, 1][:, None, None])
                & (det != 0)
            )
            with np.errstate(invalid="ignore"):
                z = l0 * a[..., 2] + l1 * b[..., 2] + l2 * c[..., 2]
            t_idx, r_idx, c_idx = np.nonzero(inside)
            pix = cy[t_idx, r_idx, c_idx] * ws + cx[t_idx, r_idx, c_idx]
            zz = z[t_idx, r_idx, c_idx]
            order = np.lexsort((zz, pix))
            pix, first = np.unique(pix[order], return_index=True)
            sel = order[first]
            better = zz[sel] < depth[pix]
            pix, sel = pix[better], sel[better]
            depth[pix] = zz[sel]
            tri_id[pix] = ids[t_idx[sel]]
            bary[pix] = np.stack([l0, l1, l2], -1)[t_idx[sel], r_idx[sel], c_idx[sel]]
    return depth.reshape(hs, ws), tri_id.reshape(hs, ws), bary.reshape(hs, ws, 3)


def mesh_points(
    tablet: MeshTablet,
    pose: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    t_xy: np.ndarray,
    step: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth z (len(ys), len(xs)) µm in the view frame (inf: none), flat triangle normals
    (NaN: none) and linear RGB albedo of the mesh at pose·X + t_xy, on the grid (xs, ys)."""
    verts = tablet.vertices_um @ pose.T + t_xy
    tri = verts[tablet.faces]
    depth, tri_id, bary = _rasterise(tri, xs, ys, step)
    hit = tri_id >= 0
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    normals = np.full((*depth.shape, 3), np.nan)
    normals[hit] = n[tri_id[hit]]
    # The camera sees the side facing it whatever the file's winding: n_z < 0.
    normals[hit] *= np.where(normals[hit][:, 2:] > 0, -1.0, 1.0)
    if tablet.vertex_rgb is None:
        albedo = np.broadcast_to(np.array(CLAY_RGB, np.float32), (*depth.shape, 3))
    else:
        corner = tablet.vertex_rgb[tablet.faces[tri_id[hit]]]  # (N, 3 corners, 3)
        albedo = np.zeros((*depth.shape, 3), np.float32)
        albedo[hit] = np.einsum("nk,nkc->nc", bary[hit], corner)
    return depth, normals, albedo


def render_mesh_view(
    tablet: MeshTablet,
    pose: np.ndarray,
    *,
    width: int,
    height: int,
    pixel_size_um: float,
    supersample: int,
    centre_um: tuple[float, float] = (0.0, 0.0),
) -> View:
    """The mesh seen through ``pose`` (rotation tablet→view), like ``render_view``."""
    pose = np.asarray(pose, float)
    if pose.shape != (3, 3) or not np.allclose(pose @ pose.T, np.eye(3), atol=1e-6):
        raise ValueError("pose must be a 3×3 rotation matrix")
    xs = sample_coords_um(width, pixel_size_um, supersample)
    ys = sample_coords_um(height, pixel_size_um, supersample)
    t_xy = np.array(
        [
            (width - 1) / 2 * pixel_size_um + centre_um[0],
            (height - 1) / 2 * pixel_size_um + centre_um[1],
            0.0,
        ]
    )
    depth, normals, albedo = mesh_points(tablet, pose, xs, ys, t_xy, pixel_size_um / supersample)
    return assemble_view(
        width, height, pixel_size_um, supersample, depth, normals, albedo, pose, t_xy
    )
