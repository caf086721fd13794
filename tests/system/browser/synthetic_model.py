"""A small synthetic tablet face as a model directory, for the browser tests.

Ground truth is analytic, so the tests know what the viewer must show:

- the surface is a "pillow" h0(x, y) = PILLOW_UM (1 - u^2)(1 - v^2) (u, v in [-1, 1] across the
  face) with cuneiform-like wedges pressed into it: V-grooves of depth WEDGE_DEPTH_UM;
- the GLB is DECIMATED: one vertex every MESH_STEP_PX pixels, so the wedges (a few pixels wide)
  exist only in the full-resolution ``normals.png``. A viewer that relights them exactly must
  use the object-space normal map, as docs/architecture.md asks;
- files follow SCAN_BUNDLE.md's model directory: mesh in millimetres in the scan frame, vertex
  (c s, r s, -h)/1000 for pixel (r, c), faces wound so that right-hand normals point to -z;
  texture coordinates are the image grid u = (c + 0.5)/W, v = (r + 0.5)/H.

``make_model_dir(out, seed=...)`` writes the directory and returns the geometry facts the tests
need (`ModelFacts`).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib
from PIL import Image
from scipy.ndimage import gaussian_filter

from worker.recon.gltf_frame import gltf_root_matrix, root_node

WIDTH_PX = 480
HEIGHT_PX = 320
PIXEL_SIZE_UM = 100.0
MESH_STEP_PX = 16
PILLOW_UM = 2000.0
WEDGE_DEPTH_UM = 250.0
WEDGE_HALF_WIDTH_UM = 600.0

# The long vertical test groove: its left wall faces +x (the right edge), its right wall -x.
GROOVE_X_MM = 24.0
GROOVE_Y_MM = (6.0, 26.0)


@dataclass(frozen=True)
class ModelFacts:
    width_px: int
    height_px: int
    pixel_size_um: float
    groove_x_mm: float
    groove_y_mm: tuple[float, float]
    groove_half_width_mm: float
    mesh_vertex_mm: dict  # (row, col) pixel of a mesh vertex -> its (x, y, z) in mm


def _pillow_um(x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
    u = 2 * x_um / ((WIDTH_PX - 1) * PIXEL_SIZE_UM) - 1
    v = 2 * y_um / ((HEIGHT_PX - 1) * PIXEL_SIZE_UM) - 1
    return PILLOW_UM * (1 - u**2) * (1 - v**2)


def _wedges_um(x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
    """Depth (≥ 0, µm) of the wedge impressions: vertical and horizontal V-grooves."""
    depth = np.zeros_like(x_um)
    hw = WEDGE_HALF_WIDTH_UM
    # the long vertical groove of the lighting test
    inside = (y_um >= GROOVE_Y_MM[0] * 1e3) & (y_um <= GROOVE_Y_MM[1] * 1e3)
    v = WEDGE_DEPTH_UM * np.clip(1 - np.abs(x_um - GROOVE_X_MM * 1e3) / hw, 0, None)
    depth = np.maximum(depth, np.where(inside, v, 0))
    # short horizontal wedges, tapering from a deep head: a line of "signs"
    for k in range(5):
        x0 = (5.0 + 3.0 * k) * 1e3
        y0 = (8.0 + 4.0 * (k % 2)) * 1e3
        length = 2.4e3
        t = np.clip((x_um - x0) / length, 0, 1)
        along = (x_um >= x0) & (x_um <= x0 + length)
        w = hw * (1 - 0.7 * t)
        v = WEDGE_DEPTH_UM * (1 - 0.6 * t) * np.clip(1 - np.abs(y_um - y0) / w, 0, None)
        depth = np.maximum(depth, np.where(along, v, 0))
    for k in range(4):
        x0 = (30.0 + 3.5 * k) * 1e3
        y0 = 20.0e3
        length = 2.6e3
        t = np.clip((y_um - y0) / length, 0, 1)
        along = (y_um >= y0) & (y_um <= y0 + length)
        w = hw * (1 - 0.7 * t)
        v = WEDGE_DEPTH_UM * (1 - 0.6 * t) * np.clip(1 - np.abs(x_um - x0) / w, 0, None)
        depth = np.maximum(depth, np.where(along, v, 0))
    return depth


def height_um(rows: np.ndarray, cols: np.ndarray, *, wedges: bool = True) -> np.ndarray:
    """Height (µm, toward the camera) at pixel positions."""
    x = cols * PIXEL_SIZE_UM
    y = rows * PIXEL_SIZE_UM
    h = _pillow_um(x, y)
    return h - _wedges_um(x, y) if wedges else h


def _png_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def _glb(positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray) -> bytes:
    blobs = [
        positions.astype("<f4").tobytes(),
        normals.astype("<f4").tobytes(),
        uvs.astype("<f4").tobytes(),
        faces.astype("<u4").tobytes(),
    ]
    offsets = np.cumsum([0] + [len(b) for b in blobs])
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="digital-hammurabi browser-test fixture"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        # glTF's convention as model.glb has it: a root node over the scan-frame mm mesh.
        nodes=[
            root_node(
                gltf_root_matrix(positions.min(axis=0), positions.max(axis=0)),
                [1],
                name="scan frame",
            ),
            pygltflib.Node(mesh=0, name="tablet"),
        ],
        meshes=[
            pygltflib.Mesh(
                primitives=[
                    pygltflib.Primitive(
                        attributes=pygltflib.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2),
                        indices=3,
                        material=0,
                    )
                ]
            )
        ],
        materials=[pygltflib.Material(name="clay", doubleSided=True)],
        buffers=[pygltflib.Buffer(byteLength=int(offsets[-1]))],
        bufferViews=[
            pygltflib.BufferView(buffer=0, byteOffset=int(offsets[i]), byteLength=len(blobs[i]))
            for i in range(4)
        ],
        accessors=[
            pygltflib.Accessor(
                bufferView=0,
                componentType=pygltflib.FLOAT,
                count=len(positions),
                type=pygltflib.VEC3,
                min=positions.min(axis=0).tolist(),
                max=positions.max(axis=0).tolist(),
            ),
            pygltflib.Accessor(
                bufferView=1, componentType=pygltflib.FLOAT, count=len(normals), type=pygltflib.VEC3
            ),
            pygltflib.Accessor(
                bufferView=2, componentType=pygltflib.FLOAT, count=len(uvs), type=pygltflib.VEC2
            ),
            pygltflib.Accessor(
                bufferView=3,
                componentType=pygltflib.UNSIGNED_INT,
                count=int(faces.size),
                type=pygltflib.SCALAR,
            ),
        ],
    )
    gltf.set_binary_blob(b"".join(blobs))
    return b"".join(gltf.save_to_bytes())


def make_model_dir(out: Path, *, seed: int = 0, tint: float = 0.0) -> ModelFacts:
    """Write a model directory for the synthetic face into ``out`` (created)."""
    out = Path(out)
    (out / "quality").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:HEIGHT_PX, 0:WIDTH_PX].astype(np.float64)
    h = height_um(rows, cols)

    # normals n ∝ (-dh/dx, -dh/dy, -1), facing the camera (n_z < 0)
    dh_dy, dh_dx = np.gradient(h, PIXEL_SIZE_UM)
    n = np.stack([-dh_dx, -dh_dy, -np.ones_like(h)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    normals_png = np.clip(np.round((n + 1) / 2 * 255), 0, 255).astype(np.uint8)

    # albedo: warm clay with a little mottling; tint shifts it so two versions differ
    base = np.array([0.72 + tint, 0.58, 0.44 - tint])
    mottle = gaussian_filter(rng.standard_normal((HEIGHT_PX, WIDTH_PX)), 6.0)
    mottle *= 0.04 / mottle.std()
    albedo = np.clip(base[None, None, :] + mottle[..., None], 0, 1)
    albedo_png = np.round(albedo * 255).astype(np.uint8)

    # signed mean curvature ≈ -½ ∇²h (positive on convex rims), 8-bit with 128 = 0
    lap = np.gradient(dh_dx, PIXEL_SIZE_UM, axis=1) + np.gradient(dh_dy, PIXEL_SIZE_UM, axis=0)
    curvature = -0.5 * lap  # 1/µm
    scale = 127 / max(np.percentile(np.abs(curvature), 99.5), 1e-12)
    curvature_png = np.clip(np.round(128 + curvature * scale), 0, 255).astype(np.uint8)

    # accessibility: 1 on the open surface, darker inside the wedges
    depth = height_um(rows, cols, wedges=False) - h
    access_png = np.round(255 * (1 - 0.8 * depth / WEDGE_DEPTH_UM)).astype(np.uint8)

    residual = np.abs(0.01 * rng.standard_normal(h.shape) + 0.00004 * depth).astype(np.float32)

    # the decimated mesh: a vertex every MESH_STEP_PX pixels (and on the last row/column)
    vr = np.unique(np.r_[np.arange(0, HEIGHT_PX, MESH_STEP_PX), HEIGHT_PX - 1])
    vc = np.unique(np.r_[np.arange(0, WIDTH_PX, MESH_STEP_PX), WIDTH_PX - 1])
    gr, gc = np.meshgrid(vr, vc, indexing="ij")
    gh = height_um(gr.astype(float), gc.astype(float))
    positions = np.stack(
        [gc * PIXEL_SIZE_UM / 1e3, gr * PIXEL_SIZE_UM / 1e3, -gh / 1e3], axis=-1
    ).reshape(-1, 3)
    uvs = np.stack([(gc + 0.5) / WIDTH_PX, (gr + 0.5) / HEIGHT_PX], axis=-1).reshape(-1, 2)
    vn = n[gr, gc].reshape(-1, 3)
    nr, nc = gr.shape
    idx = np.arange(nr * nc).reshape(nr, nc)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # (a, c, b): x right, y down, so a→c→b turns so that the right-hand normal points to -z
    faces = np.concatenate(
        [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]
    )
    e1 = positions[faces[:, 1]] - positions[faces[:, 0]]
    e2 = positions[faces[:, 2]] - positions[faces[:, 0]]
    if not (np.cross(e1, e2)[:, 2] < 0).all():
        raise AssertionError("fixture mesh winding: right-hand normals must point to -z")

    (out / "model.glb").write_bytes(_glb(positions, vn, uvs, faces))
    (out / "normals.png").write_bytes(_png_bytes(normals_png))
    (out / "albedo.png").write_bytes(_png_bytes(albedo_png))
    (out / "curvature.png").write_bytes(_png_bytes(curvature_png))
    (out / "accessibility.png").write_bytes(_png_bytes(access_png))
    (out / "thumbnail.png").write_bytes(_png_bytes(albedo_png[::2, ::2]))
    (out / "mask.png").write_bytes(_png_bytes(np.full(h.shape, 255, np.uint8)))
    np.save(out / "height.npy", h.astype(np.float32))
    np.save(out / "quality" / "photometric_residual.npy", residual)
    (out / "report.json").write_text(
        json.dumps(
            {
                "pixel_size_um": PIXEL_SIZE_UM,
                "image_size": {"width": WIDTH_PX, "height": HEIGHT_PX},
                "source": "synthetic browser-test fixture",
            }
        )
    )
    vertex_mm = {
        (int(r), int(c)): tuple(float(v) for v in positions[i * nc + j])
        for i, r in enumerate(vr)
        for j, c in enumerate(vc)
    }
    return ModelFacts(
        width_px=WIDTH_PX,
        height_px=HEIGHT_PX,
        pixel_size_um=PIXEL_SIZE_UM,
        groove_x_mm=GROOVE_X_MM,
        groove_y_mm=GROOVE_Y_MM,
        groove_half_width_mm=WEDGE_HALF_WIDTH_UM / 1e3,
        mesh_vertex_mm=vertex_mm,
    )
