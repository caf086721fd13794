"""The mesh of one tile: a regular grid of the level's height texels, with a skirt.

Vertices sit at the centres of the level's texels every `grid_step` texels, in the scan
frame's millimetres exactly as model.glb's mesh (SCAN_BUNDLE.md, "Frame of reference";
`worker.recon.mesh.grid_mesh`): x = c·p, y = r·p, z = −h, with c, r the texel centre in
full-resolution pixels, c = i·s + (s − 1)/2, p the pixel size in mm, h the height in mm.
The grid includes the first texel of the next tile, so two tiles of one level share their
edge vertices exactly (no crack). Between tiles of different levels a skirt hides the
gaps: each valid vertex on the tile's rectangle is repeated `skirt_mm` deeper (+z, away
from the camera) and joined to its neighbour on the edge by two triangles (the skirts of
3D Tiles / Cesium terrain, Ulrich 2002, "Rendering massive terrains using chunked level of
detail control").

TEXCOORD_0 spans the tile's texture (the level's texels [tx0, tx1) × [ty0, ty1)):
u = (i − tx0 + 0.5)/(tx1 − tx0), v likewise, as model.glb's u = (c + 0.5)/W.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worker.recon.mesh import grid_mesh, vertex_normals

__all__ = ["TileMesh", "tile_mesh"]


@dataclass(frozen=True)
class TileMesh:
    positions_mm: np.ndarray  # (n, 3) float32, scan frame
    normals: np.ndarray  # (n, 3) float32, unit, scan frame
    uv: np.ndarray  # (n, 2) float32
    indices: np.ndarray  # (3k,) uint32
    min_mm: np.ndarray  # (3,) of the surface and the skirt
    max_mm: np.ndarray


def _samples(start: int, stop: int, step: int, limit: int) -> np.ndarray:
    """start, start + step, … up to and including `stop` (the next tile's first texel),
    clipped to the level's last texel `limit − 1`."""
    idx = np.arange(start, stop + 1, step)
    if idx[-1] != stop:
        idx = np.append(idx, stop)
    return np.unique(np.minimum(idx, limit - 1))


def tile_mesh(
    level_height_um: np.ndarray,
    texel_rect: tuple[int, int, int, int],
    *,
    pixel_step: int,
    grid_step: int,
    pixel_size_um: float,
    skirt_mm: float,
) -> TileMesh | None:
    """The tile's mesh, or None when it has no triangle (no valid texel there).

    level_height_um: (h, w) heights of the whole level (NaN = no data); texel_rect: the
    tile's texels (tx0, ty0, tx1, ty1) in that level, half-open; pixel_step: s, full-res
    pixels per texel; grid_step: texels between mesh samples.
    """
    lh, lw = level_height_um.shape
    tx0, ty0, tx1, ty1 = texel_rect
    cs = _samples(tx0, tx1, grid_step, lw)
    rs = _samples(ty0, ty1, grid_step, lh)
    sub = np.asarray(level_height_um[np.ix_(rs, cs)], np.float32)
    ok = np.isfinite(sub)
    if ok.sum() < 3:
        return None
    # grid_mesh with a unit pixel gives vertices at sample indices; mapped to texel centres.
    mesh = grid_mesh(sub, ok, pixel_size_um=1000.0)
    if len(mesh.faces) == 0:
        return None
    p_mm = pixel_size_um / 1000.0
    col_px = cs[mesh.cols] * pixel_step + (pixel_step - 1) / 2.0
    row_px = rs[mesh.rows] * pixel_step + (pixel_step - 1) / 2.0
    pos = np.stack(
        [col_px * p_mm, row_px * p_mm, -sub[mesh.rows, mesh.cols].astype(np.float64) / 1000.0],
        axis=1,
    )
    uv = np.stack(
        [(cs[mesh.cols] - tx0 + 0.5) / (tx1 - tx0), (rs[mesh.rows] - ty0 + 0.5) / (ty1 - ty0)],
        axis=1,
    )
    normals = vertex_normals(pos.astype(np.float32), mesh.faces)
    faces = [mesh.faces.astype(np.int64)]
    index = np.full(sub.shape, -1, np.int64)
    index[mesh.rows, mesh.cols] = np.arange(len(pos))
    extra_pos, extra_n, extra_uv = [], [], []
    n_next = len(pos)
    for edge in (index[0, :], index[-1, :], index[:, 0], index[:, -1]):
        for a, b in zip(edge[:-1], edge[1:], strict=True):
            if a < 0 or b < 0:
                continue
            for v in (a, b):
                extra_pos.append(pos[v] + (0.0, 0.0, skirt_mm))
                extra_n.append(normals[v])
                extra_uv.append(uv[v])
            a2, b2 = n_next, n_next + 1
            n_next += 2
            faces.append(np.array([[a, b, b2], [a, b2, a2]], np.int64))
    if extra_pos:
        pos = np.concatenate([pos, np.asarray(extra_pos)])
        normals = np.concatenate([normals, np.asarray(extra_n, np.float32)])
        uv = np.concatenate([uv, np.asarray(extra_uv)])
    pos32 = pos.astype(np.float32)
    return TileMesh(
        positions_mm=pos32,
        normals=normals.astype(np.float32),
        uv=uv.astype(np.float32),
        indices=np.concatenate(faces).reshape(-1).astype(np.uint32),
        min_mm=pos32.min(axis=0),
        max_mm=pos32.max(axis=0),
    )
