"""TEMPORARY: a tiny writer of tiles/ (the issue-19 contract, /work/briefs/tiles-contract.md)
for the viewer's first tests, until the worker's tile builder is on main; then this file goes
and the tests use the real builder (one way to build tiles).

Quadtree of ``levels`` levels over a model directory's image grid; level l has 2^l × 2^l
tiles at pixel step 2^(levels-1-l); no meshopt compression (plain GLB)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pygltflib
from PIL import Image

from worker.recon.gltf_frame import gltf_root_matrix


def _img_bytes(a: np.ndarray, fmt: str) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format=fmt, **({"quality": 90} if fmt == "JPEG" else {}))
    return buf.getvalue()


def _tile_glb(pos, uv, faces, images: list[tuple[bytes, str]], dh_tile: dict) -> bytes:
    blobs = [pos.astype("<f4").tobytes(), uv.astype("<f4").tobytes(), faces.astype("<u4").tobytes()]
    blobs += [b for b, _ in images]
    pad = [(-len(b)) % 4 for b in blobs]
    offsets, o = [], 0
    for b, p in zip(blobs, pad, strict=True):
        offsets.append(o)
        o += len(b) + p
    g = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator="tiles fixture"),
        scene=0,
        scenes=[pygltflib.Scene(nodes=[0])],
        nodes=[pygltflib.Node(mesh=0, name="tile", extras={"dh_tile": dh_tile})],
        meshes=[
            pygltflib.Mesh(
                primitives=[
                    pygltflib.Primitive(
                        attributes=pygltflib.Attributes(POSITION=0, TEXCOORD_0=1),
                        indices=2,
                        material=0,
                    )
                ]
            )
        ],
        materials=[
            pygltflib.Material(
                pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                    baseColorTexture=pygltflib.TextureInfo(index=0)
                ),
                doubleSided=True,
                extras={"dh_maps": {"normals": 1, "curvature": 2, "accessibility": 3}},
            )
        ],
        samplers=[pygltflib.Sampler(magFilter=9729, minFilter=9987, wrapS=33071, wrapT=33071)],
        textures=[pygltflib.Texture(source=i, sampler=0) for i in range(len(images))],
        images=[pygltflib.Image(bufferView=3 + i, mimeType=m) for i, (_, m) in enumerate(images)],
        buffers=[pygltflib.Buffer(byteLength=o)],
        bufferViews=[
            pygltflib.BufferView(buffer=0, byteOffset=offsets[i], byteLength=len(blobs[i]))
            for i in range(len(blobs))
        ],
        accessors=[
            pygltflib.Accessor(
                bufferView=0,
                componentType=pygltflib.FLOAT,
                count=len(pos),
                type=pygltflib.VEC3,
                min=pos.min(0).tolist(),
                max=pos.max(0).tolist(),
            ),
            pygltflib.Accessor(
                bufferView=1, componentType=pygltflib.FLOAT, count=len(uv), type=pygltflib.VEC2
            ),
            pygltflib.Accessor(
                bufferView=2,
                componentType=pygltflib.UNSIGNED_INT,
                count=int(faces.size),
                type=pygltflib.SCALAR,
            ),
        ],
    )
    g.set_binary_blob(b"".join(b + b"\0" * p for b, p in zip(blobs, pad, strict=True)))
    return b"".join(g.save_to_bytes())


def write_tiles(model_dir: Path, *, pixel_size_um: float, levels: int = 3) -> dict:
    model_dir = Path(model_dir)
    h = np.load(model_dir / "height.npy").astype(np.float64)
    rows, cols = h.shape
    maps = {
        k: np.asarray(Image.open(model_dir / f"{k}.png"))
        for k in ("albedo", "normals", "curvature", "accessibility")
    }
    out = model_dir / "tiles"
    (out / "3d").mkdir(parents=True, exist_ok=True)
    s_mm = pixel_size_um / 1000
    lo = np.array([0, 0, -np.nanmax(h) / 1000])
    hi = np.array([(cols - 1) * s_mm, (rows - 1) * s_mm, -np.nanmin(h) / 1000])
    root_t = gltf_root_matrix(lo, hi)
    up = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)  # Y up→Z up
    up_inv = up.T

    def box(x0, y0, x1, y1, zlo, zhi):
        # a box in the tile frame = up-rotated scan-frame mm (the content's frame, z up)
        c = np.array([(x0 + x1) / 2 * s_mm, (y0 + y1) / 2 * s_mm, (zlo + zhi) / 2, 1])
        half = np.diag([(x1 - x0) / 2 * s_mm, (y1 - y0) / 2 * s_mm, max((zhi - zlo) / 2, 1e-3)])
        c = up @ c
        axes = (up[:3, :3] @ half).T
        return [*c[:3].tolist(), *axes.reshape(-1).tolist()]

    def node(level, x, y):
        n = 2**level
        step = 2 ** (levels - 1 - level)
        x0, x1 = cols * x // n, min(cols - 1, cols * (x + 1) // n)
        y0, y1 = rows * y // n, min(rows - 1, rows * (y + 1) // n)
        vc = np.unique(np.r_[np.arange(x0, x1, step), x1])
        vr = np.unique(np.r_[np.arange(y0, y1, step), y1])
        gr, gc = np.meshgrid(vr, vc, indexing="ij")
        gh = h[gr, gc]
        pos = np.stack([gc * s_mm, gr * s_mm, -gh / 1000], -1).reshape(-1, 3)
        tex = {k: m[y0 : y1 + 1 : step, x0 : x1 + 1 : step] for k, m in maps.items()}
        th, tw = tex["albedo"].shape[:2]
        uv = np.stack([((gc - x0) / step + 0.5) / tw, ((gr - y0) / step + 0.5) / th], -1).reshape(
            -1, 2
        )
        nr, nc = gr.shape
        idx = np.arange(nr * nc).reshape(nr, nc)
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        faces = np.concatenate(
            [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]
        )
        images = [
            (_img_bytes(np.ascontiguousarray(tex["albedo"][..., :3]), "JPEG"), "image/jpeg"),
            (_img_bytes(np.ascontiguousarray(tex["normals"][..., :3]), "PNG"), "image/png"),
            (_img_bytes(np.ascontiguousarray(tex["curvature"]), "PNG"), "image/png"),
            (_img_bytes(np.ascontiguousarray(tex["accessibility"]), "PNG"), "image/png"),
        ]
        info = {"level": level, "x": x, "y": y, "px_rect": [x0, y0, x1, y1], "pixel_step": step}
        name = f"{level}/{x}_{y}.glb"
        (out / "3d" / str(level)).mkdir(exist_ok=True)
        (out / "3d" / name).write_bytes(_tile_glb(pos, uv, faces, images, info))
        t = {
            "boundingVolume": {"box": box(x0, y0, x1, y1, -gh.max() / 1000, -gh.min() / 1000)},
            "geometricError": 0.0 if step == 1 else step * pixel_size_um * 1e-6,
            "refine": "REPLACE",
            "content": {"uri": name},
            "extras": {"dh_tile": info},
        }
        if level + 1 < levels:
            t["children"] = [node(level + 1, 2 * x + i, 2 * y + j) for j in (0, 1) for i in (0, 1)]
        return t

    root = node(0, 0, 0)
    root["transform"] = [float(v) for v in (root_t @ up_inv).T.reshape(-1)]
    tileset = {
        "asset": {"version": "1.1"},
        "geometricError": 2 * root["geometricError"],
        "root": root,
    }
    (out / "3d" / "tileset.json").write_text(json.dumps(tileset))
    (out / "height.f32").write_bytes(np.load(model_dir / "height.npy").astype("<f4").tobytes())
    index = {
        "version": 1,
        "width_px": cols,
        "height_px": rows,
        "pixel_size_um": pixel_size_um,
        "tileset": "3d/tileset.json",
        "height_raw": {
            "path": "height.f32",
            "dtype": "<f4",
            "shape": [rows, cols],
            "order": "row-major",
            "nodata": "NaN",
            "unit": "um",
        },
    }
    (out / "index.json").write_text(json.dumps(index))
    return index
