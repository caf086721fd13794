"""model.glb for the browser: a decimated grid mesh with full-resolution textures.

- Geometry: `mesh.grid_mesh(..., step)` with the step chosen so that the mesh has at most
  `max_triangles` triangles; the same millimetre coordinates as mesh.ply (SCAN_BUNDLE.md frame)
  under one root node that takes them to glTF's metres, +Y up, facing +Z (`gltf_frame`).
- TEXCOORD_0 is the image grid, u = (c + 0.5)/W, v = (r + 0.5)/H (docs/architecture.md), so any
  image-grid texture maps onto the mesh.
- baseColorTexture: the sRGB albedo (H, W).
- normalTexture: the full-resolution normals in glTF tangent space relative to the DECIMATED
  mesh: per pixel, N is the mesh's interpolated vertex normal, T the image +x (+u) direction
  made orthogonal to N, and B = cross(N, T) (TANGENT.w = +1, the formula of the glTF 2.0
  spec), which points toward −v (image up), the spec's +Y of a normal texture. The texel is
  (n·T, n·B, n·N) mapped to (x + 1)/2. The TANGENT attribute is written so that viewers do not
  have to guess (three.js uses it as is).
"""

from __future__ import annotations

import cv2
import numpy as np

from worker.recon.gltf_frame import gltf_root_matrix, root_node
from worker.recon.mesh import grid_mesh, vertex_normals

__all__ = ["decimation_step", "glb_bytes", "tangent_space_normals"]


def decimation_step(shape: tuple[int, int], max_triangles: int) -> int:
    """Smallest grid step whose full grid has at most `max_triangles` triangles."""
    rows, cols = shape
    step = 1
    while 2 * (-(-(rows - 1) // step)) * (-(-(cols - 1) // step)) > max_triangles:
        step += 1
    return step


def _frame(normal):
    """Unit T (image +x made orthogonal to N) and B = N × T for (..., 3) normals N."""
    t = normal * -normal[..., :1]  # x − (x·N)·N with x = (1, 0, 0)
    t[..., 0] += 1.0
    t /= np.maximum(_norm(t), 1e-12)
    return t, _cross(normal, t)


def _norm(v):
    """np.linalg.norm(v, axis=-1, keepdims=True) for (..., 3) arrays: the same squares summed
    in the same order, without numpy's slow reduction over a length-3 last axis."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.sqrt(x * x + y * y + z * z)[..., None]


def _cross(a, b):
    """np.cross(a, b) for (..., 3) arrays, component by component in the same order of
    operations (the same values) without its moved-axis temporaries (several times faster)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(a[..., i], b[..., j], out=out[..., k])
        out[..., k] -= a[..., j] * b[..., i]
    return out


def _lerp_index(n_out: int, samples: np.ndarray):
    """For linear interpolation onto pixels 0 … n_out−1 of values given at the increasing
    pixel positions `samples`: left and right sample index per pixel, weight of the right."""
    pos = np.interp(np.arange(n_out), samples, np.arange(len(samples)))
    left = np.clip(np.floor(pos).astype(np.intp), 0, max(len(samples) - 2, 0))
    right = np.minimum(left + 1, len(samples) - 1)
    return left, right, (pos - left).astype(np.float32)


# Rows per block of `_tangent_space_blocks` hold about this many pixels: the block's dozen
# (rows, W, 3) temporaries stay in the core's cache instead of streaming through memory.
_BLOCK_PX = 32_768


def tangent_space_normals(
    normals: np.ndarray, mesh_normal_grid: np.ndarray, rows: np.ndarray, cols: np.ndarray
) -> np.ndarray:
    """Full-resolution normals expressed in the decimated mesh's tangent frames.

    normals: (H, W, 3) unit object-space normals (NaN allowed → flat (0, 0, 1)).
    mesh_normal_grid: (len(rows), len(cols), 3) vertex normals of the decimated grid at the
    sample pixels rows × cols (increasing). Returns (H, W, 3) float32 tangent-space normals.
    The mesh normal at a pixel is the bilinear interpolation of the grid's, done one axis
    after the other, in float32 (the texture keeps 8 bits).
    """
    out = np.empty((*np.shape(normals)[:2], 3), np.float32)

    def keep(block: slice, tangent_n: np.ndarray) -> None:
        out[block] = tangent_n

    _tangent_space_blocks(normals, mesh_normal_grid, rows, cols, keep)
    return out


def _tangent_space_blocks(normals, mesh_normal_grid, rows, cols, emit) -> None:
    """`tangent_space_normals` by blocks of rows: emit(row slice, its (rows, W, 3) normals).

    Every pixel's value is computed alone (interpolation, frame, three dot products), so
    the blocks give the whole frame's values.
    """
    h, w = normals.shape[:2]
    grid = np.asarray(mesh_normal_grid, np.float32)
    r0, r1, fr = _lerp_index(h, rows)
    c0, c1, fc = _lerp_index(w, cols)
    fc = fc[None, :, None]
    step = max(1, _BLOCK_PX // w)
    for start in range(0, h, step):
        block = slice(start, min(start + step, h))
        f = fr[block, None, None]
        by_row = grid[r0[block]] * (1 - f) + grid[r1[block]] * f
        mesh_n = by_row[:, c0] * (1 - fc)
        mesh_n += by_row[:, c1] * fc
        mesh_n /= np.maximum(_norm(mesh_n), np.float32(1e-12))
        t, b = _frame(mesh_n)
        n = np.asarray(normals[block], np.float32)
        ok = np.isfinite(n[..., 0]) & np.isfinite(n[..., 1]) & np.isfinite(n[..., 2])
        n = np.where(ok[..., None], n, mesh_n)
        out = np.empty(n.shape, np.float32)
        for k, axis in enumerate((t, b, mesh_n)):
            o = out[..., k]
            np.multiply(n[..., 0], axis[..., 0], out=o)
            o += n[..., 1] * axis[..., 1]
            o += n[..., 2] * axis[..., 2]
        emit(block, out)


def _png(rgb8: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb8[..., ::-1]))
    if not ok:
        raise ValueError("texture could not be encoded as PNG")
    return buf.tobytes()


def glb_bytes(
    height_um: np.ndarray,
    mask: np.ndarray,
    normals: np.ndarray,
    albedo_srgb8: np.ndarray,
    *,
    pixel_size_um: float,
    max_triangles: int = 200_000,
    albedo_png: bytes | None = None,
) -> tuple[bytes, dict]:
    """Encode model.glb; returns (bytes, info) with info = {step, vertices, triangles}.

    height_um (H, W) µm, mask (H, W) bool, normals (H, W, 3), albedo_srgb8 (H, W, 3) uint8.
    albedo_png: albedo_srgb8's PNG encoding (as `cv2.imencode` gives it) when the caller
    has it already (the model directory's albedo.png); encoded here otherwise.
    """
    import pygltflib  # on first use: ~0.1 s of the CLI's start-up

    h, w = np.shape(height_um)
    step = decimation_step((h, w), max_triangles)
    mesh = grid_mesh(height_um, mask, pixel_size_um=pixel_size_um, step=step)
    if len(mesh.faces) == 0:
        raise ValueError("mask: no triangle can be made (fewer than 3 adjacent pixels)")
    vn = vertex_normals(mesh.vertices_mm, mesh.faces)
    rs = np.unique(np.append(np.arange(0, h, step), h - 1))
    cs = np.unique(np.append(np.arange(0, w, step), w - 1))
    grid_n = np.zeros((len(rs), len(cs), 3), np.float32)
    grid_n[..., 2] = -1.0
    grid_n[np.searchsorted(rs, mesh.rows), np.searchsorted(cs, mesh.cols)] = vn
    normal_tex = np.empty((h, w, 3), np.uint8)

    def to_texels(block: slice, tangent_n: np.ndarray) -> None:
        normal_tex[block] = np.clip(np.rint((tangent_n + 1.0) * 127.5), 0, 255)

    _tangent_space_blocks(normals, grid_n, rs, cs, to_texels)
    t, _ = _frame(vn.astype(np.float64))
    tangents = np.concatenate([t, np.ones((len(vn), 1))], axis=1).astype(np.float32)
    uv = np.stack([(mesh.cols + 0.5) / w, (mesh.rows + 0.5) / h], axis=1).astype(np.float32)

    blobs = [
        mesh.vertices_mm.astype(np.float32).tobytes(),
        vn.tobytes(),
        tangents.tobytes(),
        uv.tobytes(),
        mesh.faces.astype(np.uint32).tobytes(),
        _png(np.asarray(albedo_srgb8, np.uint8)) if albedo_png is None else albedo_png,
        _png(normal_tex),
    ]
    # One join of 4-byte-aligned pieces (concatenating in turn copied the growing buffer).
    offsets, pieces, size = [], [], 0
    for blob in blobs:
        pad = -len(blob) % 4
        offsets.append(size)
        pieces += [blob, b"\0" * pad]
        size += len(blob) + pad
    data = b"".join(pieces)
    views = [
        pygltflib.BufferView(
            buffer=0,
            byteOffset=offsets[i],
            byteLength=len(blobs[i]),
            target=(
                pygltflib.ARRAY_BUFFER
                if i < 4
                else (pygltflib.ELEMENT_ARRAY_BUFFER if i == 4 else None)
            ),
        )
        for i in range(len(blobs))
    ]
    nv = len(mesh.vertices_mm)
    v = mesh.vertices_mm
    accessors = [
        pygltflib.Accessor(
            bufferView=0,
            componentType=pygltflib.FLOAT,
            count=nv,
            type=pygltflib.VEC3,
            min=[float(x) for x in v.min(axis=0)],
            max=[float(x) for x in v.max(axis=0)],
        ),
        pygltflib.Accessor(
            bufferView=1, componentType=pygltflib.FLOAT, count=nv, type=pygltflib.VEC3
        ),
        pygltflib.Accessor(
            bufferView=2, componentType=pygltflib.FLOAT, count=nv, type=pygltflib.VEC4
        ),
        pygltflib.Accessor(
            bufferView=3, componentType=pygltflib.FLOAT, count=nv, type=pygltflib.VEC2
        ),
        pygltflib.Accessor(
            bufferView=4,
            componentType=pygltflib.UNSIGNED_INT,
            count=int(mesh.faces.size),
            type=pygltflib.SCALAR,
        ),
    ]
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="Digital Hammurabi worker"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[
            root_node(gltf_root_matrix(v.min(axis=0), v.max(axis=0)), [1], name="scan frame"),
            pygltflib.Node(mesh=0, name="tablet"),
        ],
        meshes=[
            pygltflib.Mesh(
                primitives=[
                    pygltflib.Primitive(
                        attributes=pygltflib.Attributes(
                            POSITION=0, NORMAL=1, TANGENT=2, TEXCOORD_0=3
                        ),
                        indices=4,
                        material=0,
                    )
                ]
            )
        ],
        materials=[
            pygltflib.Material(
                name="clay",
                pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                    baseColorTexture=pygltflib.TextureInfo(index=0),
                    metallicFactor=0.0,
                    roughnessFactor=1.0,
                ),
                normalTexture=pygltflib.NormalMaterialTexture(index=1),
                doubleSided=False,
            )
        ],
        samplers=[
            pygltflib.Sampler(
                magFilter=pygltflib.LINEAR,
                minFilter=pygltflib.LINEAR_MIPMAP_LINEAR,
                wrapS=pygltflib.CLAMP_TO_EDGE,
                wrapT=pygltflib.CLAMP_TO_EDGE,
            )
        ],
        images=[
            pygltflib.Image(bufferView=5, mimeType="image/png", name="albedo"),
            pygltflib.Image(bufferView=6, mimeType="image/png", name="normals"),
        ],
        textures=[pygltflib.Texture(sampler=0, source=0), pygltflib.Texture(sampler=0, source=1)],
        buffers=[pygltflib.Buffer(byteLength=len(data))],
        bufferViews=views,
        accessors=accessors,
    )
    gltf.set_binary_blob(data)
    glb = b"".join(gltf.save_to_bytes())
    return glb, {"step": step, "vertices": nv, "triangles": len(mesh.faces)}
