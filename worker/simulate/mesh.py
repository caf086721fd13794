"""The synthetic tablet as a closed triangle mesh (for registration ground truth).

Vertices are where rays aimed at the tablet centre along a cube-sphere grid of
directions first meet the carved surface; the grid's quads become two triangles each,
wound so that right-hand normals point outward. Units: mm, tablet frame.
"""

from __future__ import annotations

import numpy as np
import trimesh

from worker.simulate.raycast import cast_rays
from worker.simulate.tablet import Tablet

__all__ = ["tablet_mesh"]


def _cube_sphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (6·n·n, 3) and triangles of a cube-sphere grid (shared edges welded later)."""
    g = np.linspace(-1.0, 1.0, n)
    u, v = np.meshgrid(g, g, indexing="ij")
    one = np.ones_like(u)
    faces_xyz = [
        np.stack([one, u, v], -1),
        np.stack([-one, v, u], -1),
        np.stack([v, one, u], -1),
        np.stack([u, -one, v], -1),
        np.stack([u, v, one], -1),
        np.stack([v, u, -one], -1),
    ]
    dirs, tris = [], []
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    quad = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    for k, f in enumerate(faces_xyz):
        p = f.reshape(-1, 3)
        dirs.append(p / np.linalg.norm(p, axis=1, keepdims=True))
        tris.append(quad + k * n * n)
    return np.concatenate(dirs), np.concatenate(tris)


def tablet_mesh(tablet: Tablet, *, resolution: int = 160) -> trimesh.Trimesh:
    """Closed mesh of the tablet in mm (tablet frame), about 6·resolution² vertices."""
    if resolution < 4:
        raise ValueError("resolution must be >= 4")
    dirs, tris = _cube_sphere(resolution)
    far = 2.0 * float(np.linalg.norm(tablet.pillow.bounding_half_um))
    origins = dirs * far
    cav = tablet.cavities

    def candidates(i: int) -> np.ndarray:
        c = cav.centres_um[i]
        along = dirs @ c
        off = np.linalg.norm(c[None, :] - along[:, None] * dirs, axis=1)
        return np.flatnonzero(off <= cav.radii_um[i])

    hits = cast_rays(tablet.pillow, cav, origins, -dirs, candidates)
    t = np.where(hits.hit, hits.t_um, far)
    verts_um = origins - t[:, None] * dirs
    mesh = trimesh.Trimesh(verts_um / 1000.0, tris, process=True)
    mesh.merge_vertices()
    trimesh.repair.fix_normals(mesh)
    return mesh
