"""Triangle meshes of a height map on the pixel grid, in millimetres (SCAN_BUNDLE.md).

Vertex of pixel (r, c): (c·s, r·s, −h)/1000 mm (x right, y down, z away from the camera).
Each 2×2 cell whose four pixels are on the mask gives two triangles; a cell with exactly three
gives one (so the rim is not stair-cased). Faces are wound so that their right-hand normals
point toward the camera (−z): for a cell with corners a = (r, c), b = (r, c+1), c' = (r+1, c),
d = (r+1, c+1), (b − a) × (c' − a) = (s, 0, ·) × (0, s, ·) has +z, so the faces are
(a, c', b) and (b, c', d).

Encoders to bytes live here too (pure: arrays in, bytes out): binary little-endian PLY.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GridMesh", "grid_mesh", "ply_bytes", "vertex_normals"]


class GridMesh:
    """Vertices (N, 3) float32 mm, faces (F, 3) int32, and the pixel (r, c) of each vertex."""

    def __init__(self, vertices_mm, faces, rows, cols):
        self.vertices_mm = vertices_mm
        self.faces = faces
        self.rows = rows
        self.cols = cols


def grid_mesh(
    height_um: np.ndarray, mask: np.ndarray, *, pixel_size_um: float, step: int = 1
) -> GridMesh:
    """Mesh of the masked height map, sampling every `step`-th row and column.

    height_um: (H, W) float µm; mask: (H, W) bool (pixels with a finite height);
    pixel_size_um: s > 0; step ≥ 1 (decimation for the browser: cells of step×step pixels,
    keeping the last row/column so the mesh spans the whole mask).
    """
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool) & np.isfinite(h)
    if h.ndim != 2 or m.shape != h.shape:
        raise ValueError(f"height_um and mask must be the same (H, W), got {h.shape}, {m.shape}")
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    if step < 1:
        raise ValueError(f"step must be ≥ 1, got {step}")
    rows_all, cols_all = h.shape
    rs = _samples(rows_all, step)
    cs = _samples(cols_all, step)
    sub_m = m[np.ix_(rs, cs)]
    sub_h = h[np.ix_(rs, cs)]
    # int32 like the faces (and half the memory traffic of the gathers below).
    index = np.full(sub_m.shape, -1, np.int32)
    index[sub_m] = np.arange(int(sub_m.sum()), dtype=np.int32)
    rr, cc = np.nonzero(sub_m)
    r_px, c_px = rs[rr], cs[cc]
    s_mm = pixel_size_um / 1000.0
    verts = np.stack(
        [c_px * s_mm, r_px * s_mm, -sub_h[rr, cc].astype(np.float64) / 1000.0], axis=1
    ).astype(np.float32)

    a = index[:-1, :-1]
    b = index[:-1, 1:]
    c = index[1:, :-1]
    d = index[1:, 1:]
    ia, ib, ic, id_ = a >= 0, b >= 0, c >= 0, d >= 0
    full = ia & ib & ic & id_
    tris = [
        np.stack([a[full], c[full], b[full]], 1),
        np.stack([b[full], c[full], d[full]], 1),
    ]
    # Cells with exactly three corners: one triangle, same winding (right-hand normal to −z).
    three = (ia.view(np.uint8) + ib.view(np.uint8) + ic.view(np.uint8) + id_.view(np.uint8)) == 3
    for miss, tri in (
        (~ia, (b, c, d)),
        (~ib, (a, c, d)),
        (~ic, (a, d, b)),
        (~id_, (a, c, b)),
    ):
        sel = three & miss
        tris.append(np.stack([t[sel] for t in tri], 1))
    faces = np.concatenate(tris).astype(np.int32)
    return GridMesh(verts, faces, r_px.astype(np.int32), c_px.astype(np.int32))


def _samples(n: int, step: int) -> np.ndarray:
    idx = np.arange(0, n, step)
    if idx[-1] != n - 1:
        idx = np.append(idx, n - 1)
    return idx


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3) float32, oriented like the faces."""
    v = vertices.astype(np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    out = np.zeros_like(v)
    for k in range(3):
        out += np.stack(
            [np.bincount(faces[:, k], weights=fn[:, j], minlength=len(v)) for j in range(3)], 1
        )
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(norm > 0, out / norm, np.array([0.0, 0.0, -1.0]))
    return out.astype(np.float32)


def ply_bytes(
    vertices_mm: np.ndarray,
    faces: np.ndarray,
    *,
    normals: np.ndarray,
    colors_rgb8: np.ndarray,
    comment: str = "Digital Hammurabi reconstruction, mm, SCAN_BUNDLE.md frame",
) -> bytes:
    """Binary little-endian PLY: vertex x y z nx ny nz (float32) red green blue (uchar),
    face list (uchar count, int32 indices)."""
    n = len(vertices_mm)
    if np.shape(normals) != (n, 3) or np.shape(colors_rgb8) != (n, 3):
        raise ValueError("normals and colors_rgb8 must be (N, 3) like vertices_mm")
    vdt = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        + [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )
    vert = np.empty(n, vdt)
    for i, k in enumerate(("x", "y", "z")):
        vert[k] = vertices_mm[:, i]
    for i, k in enumerate(("nx", "ny", "nz")):
        vert[k] = np.nan_to_num(normals[:, i])
    for i, k in enumerate(("red", "green", "blue")):
        vert[k] = colors_rgb8[:, i]
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    face = np.empty(len(faces), fdt)
    face["n"] = 3
    face["i"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment {comment}\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(faces)}\n"
        "property list uchar int vertex_indices\n"
        "end_header\n"
    )
    return header.encode("ascii") + vert.tobytes() + face.tobytes()
