"""Tiles of a registered whole tablet (docs/tiles.md, "Whole tablet").

`tiles/faces/<label>/` holds each face's tiles as a face model's `tiles/`, built from the
face's model directory but with the whole tablet's own maps of the face where it has them
(`blended_maps`: the normals and albedo blended across the seams, the face's weight in the
normals' alpha, exactly what model.glb's viewer draws), and its tileset's root.transform is
the face's scan → tablet transform (mm, transforms.json); `tiles/3d/tileset.json` is the root: its
root.transform takes the tablet frame (mm) to glTF metres, +Y up (model.glb's root node),
and its children reference the faces' tilesets (3D Tiles 1.1 "external tilesets"), so the
whole tablet streams face by face. `tiles/index.json` (written last) lists the faces'
index.json files; `tiles/files.json` every file.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import cv2
import numpy as np
import pygltflib

from worker.durable import replace_dir_atomic, write_file_atomic
from worker.recon.gltf_frame import gltf_root_matrix
from worker.recon.shading_maps import normals_rgb8
from worker.tiles.build import (
    TileError,
    fill_tiles,
    glb_root_matrix,
    read_gloss,
    write_file_list,
)

__all__ = ["blended_maps", "build_tablet_tiles", "glb_node_albedos", "transformed_box"]


def transformed_box(box: list[float], matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) of a 3D Tiles box's corners after the 4×4 `matrix`."""
    c = np.array(box[:3])
    axes = np.array(box[3:]).reshape(3, 3)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    corners = c + signs @ axes
    moved = corners @ np.asarray(matrix)[:3, :3].T + np.asarray(matrix)[:3, 3]
    return moved.min(axis=0), moved.max(axis=0)


def _face_arrays(face_dir: Path, blended: dict | None = None) -> dict:
    """What fill_tiles needs from a face model directory (normals.png made from normals.npy
    when the directory has none, as the registration job fetches it); ``blended``: the whole
    tablet's own maps of the face (`blended_maps`), used instead of the face model's."""
    try:
        report = json.loads((face_dir / "report.json").read_text(encoding="utf-8"))
        pixel_size_um = float(report["pixel_size_um"])
        height = np.load(face_dir / "height.npy", mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TileError(f"model directory {face_dir}: {exc}") from None

    def read(name: str, flags: int) -> np.ndarray:
        img = cv2.imread(str(face_dir / name), flags)
        if img is None:
            raise TileError(f"{face_dir}: {name} is missing or unreadable")
        return np.ascontiguousarray(img[..., ::-1]) if img.ndim == 3 else img

    blended = {k: v for k, v in (blended or {}).items() if v.shape[:2] == height.shape}
    if "normals" in blended:
        normals = blended["normals"]
    elif (face_dir / "normals.png").is_file():
        normals = read("normals.png", cv2.IMREAD_COLOR)
    else:
        normals = normals_rgb8(np.load(face_dir / "normals.npy", allow_pickle=False))
    return {
        "height_um": height,
        "albedo": blended["albedo"]
        if "albedo" in blended
        else read("albedo.png", cv2.IMREAD_COLOR),
        "normals_rgb8": normals,
        "curvature8": read("curvature.png", cv2.IMREAD_GRAYSCALE),
        "accessibility8": read("accessibility.png", cv2.IMREAD_GRAYSCALE),
        "pixel_size_um": pixel_size_um,
        "gloss": read_gloss(face_dir),
    }


def blended_maps(model_dir: Path, folder: str) -> dict[str, np.ndarray]:
    """The whole tablet's maps of the face in ``folder`` (faces/<label>), as the single-mesh
    viewer draws them (worker.register.run.whole_tablet_model): ``normals`` (H, W, 4) RGBA,
    the normals blended across the seams with the face's weight in alpha (normals.png), and
    ``albedo`` (H, W, 3), blended likewise (the baseColorTexture of the face's node in
    model.glb). Either is absent when the model has no such map (tiles of face models only)."""
    out = {}
    img = cv2.imread(str(model_dir / folder / "normals.png"), cv2.IMREAD_UNCHANGED)
    if img is not None and img.ndim == 3 and img.shape[2] == 4 and img.dtype == np.uint8:
        out["normals"] = np.ascontiguousarray(img[..., [2, 1, 0, 3]])
    albedo = glb_node_albedos(model_dir / "model.glb").get(folder)
    if albedo is not None:
        out["albedo"] = albedo
    return out


def glb_node_albedos(glb_path: Path) -> dict[str, np.ndarray]:
    """{face_asset_dir(node name): its baseColorTexture (H, W, 3) RGB uint8} of a whole
    tablet's model.glb (one node per face); {} when there is no such GLB or it is unreadable."""
    from worker.register.io import face_asset_dir

    if not glb_path.is_file():
        return {}
    try:
        gltf = pygltflib.GLTF2().load(str(glb_path))
        blob = gltf.binary_blob()
    except Exception:  # an unreadable GLB: the faces' own albedo is tiled instead
        return {}
    out = {}
    for node in gltf.nodes:
        try:
            prim = gltf.meshes[node.mesh].primitives[0]
            tex = gltf.materials[prim.material].pbrMetallicRoughness.baseColorTexture
            image = gltf.images[gltf.textures[tex.index].source]
            view = gltf.bufferViews[image.bufferView]
        except (TypeError, IndexError, AttributeError):
            continue  # a node without a mesh (the root) or without a texture
        start = view.byteOffset or 0
        data = np.frombuffer(blob[start : start + view.byteLength], np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if img is not None and node.name:
            out[face_asset_dir(node.name)] = np.ascontiguousarray(img[..., ::-1])
    return out


def build_tablet_tiles(
    model_dir: str | os.PathLike,
    faces: Mapping[str, tuple[Path, np.ndarray]],
    *,
    progress: Callable[[str, float], None] | None = None,
) -> dict:
    """Build `model_dir/tiles/` of a whole-tablet model: `faces` maps each face's folder
    name (``faces/<label>`` relative to tiles/) to (its model directory, its 4×4 scan →
    tablet transform in mm). Returns index.json's dict."""
    model_dir = Path(model_dir)
    progress = progress or (lambda stage, fraction: None)
    if not faces:
        raise TileError("a whole tablet needs at least one face to tile")
    # Each face from the whole tablet's blended maps where the model has them (the normals'
    # alpha is the face's weight: the viewer draws, where faces overlap, the face of larger
    # weight, as it does on model.glb), else from the face model's own.
    arrays = {
        folder: (_face_arrays(d, blended_maps(model_dir, folder)), np.asarray(t, float))
        for folder, (d, t) in faces.items()
    }
    written: dict = {}

    def fill(tmp: Path) -> None:
        t0 = time.perf_counter()
        children, indexes = [], {}
        lo_all, hi_all = None, None
        for k, (folder, (face, matrix)) in enumerate(arrays.items()):
            sub = tmp / folder
            sub.mkdir(parents=True)

            def face_progress(stage: str, f: float, k=k) -> None:
                progress(stage, (k + f) / len(arrays))

            indexes[folder] = fill_tiles(sub, **face, root_matrix=matrix, progress=face_progress)
            face_set = json.loads((sub / "3d" / "tileset.json").read_text())
            lo, hi = transformed_box(face_set["root"]["boundingVolume"]["box"], matrix)
            lo_all = lo if lo_all is None else np.minimum(lo_all, lo)
            hi_all = hi if hi_all is None else np.maximum(hi_all, hi)
            children.append(
                {
                    "boundingVolume": {"box": _box(lo, hi)},
                    "geometricError": face_set["geometricError"],
                    "refine": "REPLACE",
                    "content": {"uri": f"../{folder}/3d/tileset.json"},
                    "extras": {"dh_face": folder.rsplit("/", 1)[-1]},
                }
            )
        root_matrix = glb_root_matrix(model_dir / "model.glb")
        if root_matrix is None:
            root_matrix = gltf_root_matrix(lo_all, hi_all)
        diagonal_m = float(np.linalg.norm(hi_all - lo_all)) / 1000.0
        tileset = {
            "asset": {
                "version": "1.1",
                "generator": "Digital Hammurabi worker.tiles",
                "extras": {
                    "frame": "root.transform takes the tablet frame (mm, transforms.json) "
                    "to glTF metres, +Y up, as model.glb's root node; each face's tileset "
                    "carries its scan -> tablet transform"
                },
            },
            "geometricError": diagonal_m,
            "root": {
                "transform": [float(v) for v in np.asarray(root_matrix, float).T.reshape(-1)],
                "boundingVolume": {"box": _box(lo_all, hi_all)},
                "geometricError": max(c["geometricError"] for c in children),
                "refine": "REPLACE",
                "children": children,
            },
        }
        (tmp / "3d").mkdir()
        (tmp / "3d" / "tileset.json").write_text(json.dumps(tileset), encoding="utf-8")
        total = write_file_list(tmp)
        stats = {
            "seconds": round(time.perf_counter() - t0, 3),
            "bytes": total,
            "tiles_3d": sum(i["stats"]["tiles_3d"] for i in indexes.values()),
            "tiles_iiif": sum(i["stats"]["tiles_iiif"] for i in indexes.values()),
            "levels": max(i["stats"]["levels"] for i in indexes.values()),
        }
        index = {
            "version": 1,
            "tileset": "3d/tileset.json",
            "faces": {folder: f"{folder}/index.json" for folder in indexes},
            "files": "files.json",
            "stats": stats,
        }
        write_file_atomic(tmp / "index.json", json.dumps(index, indent=1).encode())
        written["index"] = index

    replace_dir_atomic(model_dir / "tiles", fill)
    progress("tiles: done", 1.0)
    return written["index"]


def _box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    c = (lo + hi) / 2.0
    h = np.maximum((hi - lo) / 2.0, 1e-6)
    return [float(v) for v in (*c, h[0], 0, 0, 0, h[1], 0, 0, 0, h[2])]
