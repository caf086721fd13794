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
        unit = p / np.linalg.norm(p, axis=1, keepdims=True)
        # Wind each cube face so that right-hand normals point away from the centre.
        a0, b0, c0 = unit[quad[0]]
        flip = np.cross(b0 - a0, c0 - a0) @ (a0 + b0 + c0) < 0
        dirs.append(unit)
        tris.append((quad[:, ::-1] if flip else quad) + k * n * n)
    return np.concatenate(dirs), np.concatenate(tris)


def tablet_mesh(tablet: Tablet, *, resolution: int = 128) -> trimesh.Trimesh:
    """Closed mesh of the tablet in mm (tablet frame), about 6·resolution² vertices."""
    if resolution < 4:
        raise ValueError("resolution must be >= 4")
    dirs, tris = _cube_sphere(resolution)
    far = 2.0 * float(np.linalg.norm(tablet.pillow.bounding_half_um))
    origins = dirs * far
    cav = tablet.cavities

    # Rays run along lines through the origin: the line along d passes within r of a cavity
    # centre c when (d·c)² >= |c|² - r², on c's side of the origin when d·c > 0.
    lists: list[np.ndarray] = []
    for k0 in range(0, len(cav), 64):
        centres = cav.centres_um[k0 : k0 + 64]
        along = (dirs @ centres.T).astype(np.float32)
        reach = np.sum(centres**2, axis=1) - cav.radii_um[k0 : k0 + 64] ** 2
        near = (along > 0) & (along * along >= reach) | (reach <= 0)
        lists += [np.flatnonzero(near[:, j]) for j in range(near.shape[1])]

    def candidates(i: int) -> np.ndarray:
        return lists[i]

    hits = cast_rays(tablet.pillow, cav, origins, -dirs, candidates)
    t = np.where(hits.hit, hits.t_um, far)
    verts_um = origins - t[:, None] * dirs
    mesh = trimesh.Trimesh(verts_um / 1000.0, tris, process=False)
    mesh.merge_vertices()
    return mesh
