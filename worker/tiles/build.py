"""Build `tiles/` of a model directory (docs/tiles.md; the contract of issue 19).

I/O at the edge: reads height.npy, albedo.png, normals.png, curvature.png,
accessibility.png, report.json and model.glb of the model directory; writes `tiles/`
through a temporary folder renamed into place (`worker.durable.replace_dir_atomic`), with
`tiles/index.json` written last, then adds the tiling figures to report.json.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pygltflib

from worker.durable import replace_dir_atomic, write_file_atomic
from worker.recon.gltf_frame import EXTRAS_KEY, gltf_root_matrix
from worker.tiles import quadtree
from worker.tiles.iiif import save_layer
from worker.tiles.pyramid import halve_height, halve_image, height_level0
from worker.tiles.tile_glb import tile_glb_bytes
from worker.tiles.tile_mesh import tile_mesh

__all__ = [
    "GRID_CELLS",
    "TEXTURE_PX",
    "TileError",
    "build_tiles",
    "fill_tiles",
    "glb_root_matrix",
    "read_gloss",
]

log = logging.getLogger("worker.tiles")

TEXTURE_PX = 512  # texels per side of a 3D tile's textures
GRID_CELLS = 128  # mesh cells per side of a 3D tile
JPEG_QUALITY = 90
Progress = Callable[[str, float], None]


class TileError(ValueError):
    """The model directory lacks what the tiles are made from."""


def _read_grey_or_rgb(path: Path, *, rgb: bool) -> np.ndarray:
    if not path.is_file():
        raise TileError(f"{path.parent}: {path.name} is missing (derive the assets first)")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR if rgb else cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise TileError(f"{path}: not a readable image")
    return np.ascontiguousarray(img[..., ::-1]) if rgb else img


def _encode(image: np.ndarray, ext: str, name: str) -> bytes:
    # OpenCV writes BGR(A): RGB → BGR, RGBA → BGRA.
    img = image if image.ndim == 2 else image[..., [2, 1, 0, 3][: image.shape[2]]]
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if ext == ".jpg" else []
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(img), params)
    if not ok:
        raise OSError(f"{name}: {ext} encoding failed")
    return buf.tobytes()


def read_gloss(model_dir: Path) -> tuple[np.ndarray, dict] | None:
    """The model's measured gloss (worker/photos.py): (gloss.png's red channel (H, W) uint8,
    {"strength_scale", "exponent"}), or None when the scan has none or its fit stood down
    (gloss.json without both > 0, as the viewer's assets.js decides) or a file is unreadable."""
    try:
        info = json.loads((model_dir / "gloss.json").read_text(encoding="utf-8"))
        scale, exponent = float(info["strength_scale"]), float(info["exponent"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    img = cv2.imread(str(model_dir / "gloss.png"), cv2.IMREAD_COLOR)
    if img is None or not (scale > 0 and exponent > 0):
        return None
    red = np.ascontiguousarray(img[..., 2])  # OpenCV reads BGR
    return red, {"strength_scale": scale, "exponent": exponent}


def height_png_mapping(height_um: np.ndarray) -> tuple[float, float]:
    """(offset_um a, scale_um b) with height_um = a + b·v for 16-bit v ∈ 1 … 65535; v = 0 is
    no data. b spreads the finite range over the 65535 values."""
    lo, hi = float(np.nanmin(height_um)), float(np.nanmax(height_um))
    scale = (hi - lo) / 65534.0 if hi > lo else 1.0
    return lo - scale, scale


def height_png16(height_um: np.ndarray, offset_um: float, scale_um: float) -> np.ndarray:
    """16-bit grey values of `height_png_mapping`, 0 where the height is NaN, by row blocks."""
    h, w = height_um.shape
    out = np.zeros((h, w), np.uint16)
    step = max(1, (1 << 22) // max(w, 1))
    for r in range(0, h, step):
        block = np.asarray(height_um[r : r + step], np.float32)
        v = np.rint((block - offset_um) / scale_um)
        out[r : r + step] = np.where(np.isfinite(block), np.clip(v, 1, 65535), 0)
    return out


def glb_root_matrix(glb_path: Path) -> np.ndarray | None:
    """model.glb's scan → glTF root matrix (so that tiles and model.glb coincide), or None
    when there is no such GLB (then the tiles' own bounds give the same construction)."""
    if not glb_path.is_file():
        return None
    try:
        gltf = pygltflib.GLTF2().load(str(glb_path))
    except Exception:  # unreadable: the matrix is computed from the tiles, never fatal
        return None
    for node in gltf.nodes:
        if node.extras and EXTRAS_KEY in node.extras and node.matrix:
            return np.asarray(node.matrix, float).reshape(4, 4).T
    return None


def _box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    """3D Tiles boundingVolume.box: centre then the three half-axis vectors."""
    c = (lo + hi) / 2.0
    h = np.maximum((hi - lo) / 2.0, 1e-6)
    return [float(v) for v in (*c, h[0], 0, 0, 0, h[1], 0, 0, 0, h[2])]


class _Writer:
    """Writes files in a background thread (each fsynced); remembers names and sizes."""

    def __init__(self, root: Path):
        self.root = root
        self.pool = ThreadPoolExecutor(max_workers=1)
        self.jobs = []

    def put(self, name: str, data: bytes) -> None:
        path = self.root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        self.jobs.append(self.pool.submit(_write_fsync, path, data))

    def wait(self) -> None:
        for job in self.jobs:
            job.result()
        self.jobs.clear()
        self.pool.shutdown()


def _write_fsync(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _fsync_tree_files(root: Path) -> None:
    for path in root.rglob("*"):
        if path.is_file():
            with open(path, "rb") as fh:
                os.fsync(fh.fileno())


def write_file_list(root: Path) -> int:
    """Write root/files.json (relative name → size_bytes, sha256 of every file below root:
    what the API may serve under tiles/) and return the files' total bytes."""
    files = {}
    for path in sorted(root.rglob("*")):
        if path.is_file():
            data = path.read_bytes()
            rel = path.relative_to(root).as_posix()
            files[rel] = {"size_bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    write_file_atomic(root / "files.json", json.dumps(files, separators=(",", ":")).encode())
    return sum(f["size_bytes"] for f in files.values())


def fill_tiles(
    tmp: Path,
    *,
    height_um: np.ndarray,
    albedo: np.ndarray,
    normals_rgb8: np.ndarray,
    curvature8: np.ndarray,
    accessibility8: np.ndarray,
    pixel_size_um: float,
    root_matrix: np.ndarray | None = None,
    albedo_path: Path | None = None,
    normals_path: Path | None = None,
    gloss: tuple[np.ndarray, dict] | None = None,
    progress: Progress = lambda stage, fraction: None,
) -> dict:
    """Write the content of `tiles/` into the empty folder `tmp`; returns index.json's dict.

    height_um (H, W) float (NaN = no data; may be a memory map); albedo (H, W, 3) sRGB uint8;
    normals_rgb8 (H, W, 3) = (n + 1)/2 · 255, or (H, W, 4) with a whole tablet's face weight
    in alpha (worker.register.merge.face_normal_map: the 3D tiles keep it, the IIIF layer
    shows RGB); curvature8, accessibility8 (H, W) uint8 as worker.assets writes them.
    albedo_path / normals_path: the same images as files (RGB), which libvips streams instead
    of copying the arrays. gloss: (gloss.png's pixels (H, W[, C]) uint8, {"strength_scale",
    "exponent"} of gloss.json), the scan's measured gloss (worker/photos.py), or None.
    """
    t_start = time.perf_counter()
    H, W = height_um.shape
    for name, arr in (
        ("albedo", albedo),
        ("normals", normals_rgb8),
        ("curvature", curvature8),
        ("accessibility", accessibility8),
    ):
        if arr.shape[:2] != (H, W):
            raise TileError(f"{name}: {arr.shape[:2]} differs from height's {(H, W)}")
    if gloss is not None and gloss[0].shape[:2] != (H, W):
        # An extra, as in the model: the tiles are made without it rather than not at all.
        log.warning("gloss: %s differs from height's %s; tiled without", gloss[0].shape, (H, W))
        gloss = None
    rows = max(1, (1 << 22) // W)
    if not any(np.isfinite(height_um[r : r + rows]).any() for r in range(0, H, rows)):
        raise TileError("height: no finite value")

    # 1. The raw heights for the viewer's Range reads.
    progress("tiles: heights", 0.0)
    with open(tmp / "height.f32", "wb") as fh:
        step = max(1, (1 << 22) // W)
        for r in range(0, H, step):
            fh.write(np.ascontiguousarray(height_um[r : r + step], "<f4").tobytes())
        fh.flush()
        os.fsync(fh.fileno())

    # 2. IIIF image pyramids.
    progress("tiles: iiif", 0.05)
    offset_um, scale_um = height_png_mapping(np.asarray(height_um))
    (tmp / "iiif").mkdir()
    n_iiif = save_layer(albedo_path or albedo, tmp / "iiif" / "albedo", suffix=".jpg[Q=90]")
    n_iiif += save_layer(
        normals_path or normals_rgb8[..., :3], tmp / "iiif" / "normals", suffix=".png"
    )
    n_iiif += save_layer(
        height_png16(height_um, offset_um, scale_um), tmp / "iiif" / "height", suffix=".png"
    )
    progress("tiles: iiif", 0.25)

    # 3. The 3D tileset, level by level from the finest (pyramids are built on the way).
    levels = quadtree.level_count(W, H, TEXTURE_PX)
    grid_step = max(1, TEXTURE_PX // GRID_CELLS)
    writer = _Writer(tmp / "3d")
    heights = height_level0(height_um)
    images = {
        "albedo": albedo,
        "normals": normals_rgb8,
        "curvature": curvature8,
        "accessibility": accessibility8,
    }
    material_extras = None
    if gloss is not None:
        # The red channel: round(255 · k_s / strength_scale) (worker/photos.py).
        images["gloss"] = gloss[0] if gloss[0].ndim == 2 else gloss[0][..., 0]
        material_extras = {"dh_gloss": gloss[1]}
    nodes: dict[tuple[int, int, int], dict] = {}
    total_tiles = sum(
        len(quadtree.tiles_of_level(lv, levels, W, H, TEXTURE_PX)) for lv in range(levels)
    )
    done = 0
    for level in range(levels - 1, -1, -1):
        s = quadtree.pixel_step(level, levels)
        level_h = heights.height_um()
        error_m = quadtree.geometric_error_m(level, levels, TEXTURE_PX, GRID_CELLS, pixel_size_um)
        for tile in quadtree.tiles_of_level(level, levels, W, H, TEXTURE_PX):
            x0, y0, x1, y1 = tile.px_rect
            texels = (x0 // s, y0 // s, -(-x1 // s), -(-y1 // s))
            node: dict = {
                "geometricError": error_m,
                "refine": "REPLACE",
                "extras": {
                    "dh_tile": {
                        "level": level,
                        "x": tile.x,
                        "y": tile.y,
                        "px_rect": list(tile.px_rect),
                        "pixel_step": s,
                    }
                },
            }
            lo, hi = None, None
            mesh = tile_mesh(
                level_h,
                texels,
                pixel_step=s,
                grid_step=grid_step,
                pixel_size_um=pixel_size_um,
                skirt_mm=_skirt_mm(level_h, texels, grid_step * s * pixel_size_um / 1000.0),
            )
            if mesh is not None:
                tx0, ty0, tx1, ty1 = texels
                crop = {k: v[ty0:ty1, tx0:tx1] for k, v in images.items()}
                textures = {
                    "albedo": (_encode(crop["albedo"], ".jpg", "albedo"), "image/jpeg"),
                    "normals": (_encode(crop["normals"], ".png", "normals"), "image/png"),
                    "curvature": (_encode(crop["curvature"], ".png", "curvature"), "image/png"),
                    "accessibility": (
                        _encode(crop["accessibility"], ".png", "accessibility"),
                        "image/png",
                    ),
                }
                if "gloss" in crop:
                    textures["gloss"] = (_encode(crop["gloss"], ".png", "gloss"), "image/png")
                uri = f"{level}/{tile.x}_{tile.y}.glb"
                glb = tile_glb_bytes(
                    mesh, textures, extras=node["extras"], material_extras=material_extras
                )
                writer.put(uri, glb)
                node["content"] = {"uri": uri}
                lo, hi = mesh.min_mm.astype(float), mesh.max_mm.astype(float)
            kids = [
                nodes.pop((c.level, c.x, c.y))
                for c in quadtree.children(tile, levels, W, H, TEXTURE_PX)
                if (c.level, c.x, c.y) in nodes
            ]
            for kid in kids:
                klo, khi = kid.pop("_lo"), kid.pop("_hi")
                lo = klo if lo is None else np.minimum(lo, klo)
                hi = khi if hi is None else np.maximum(hi, khi)
            if kids:
                node["children"] = kids
            done += 1
            if lo is None:
                continue  # no surface here nor below
            node["_lo"], node["_hi"] = lo, hi
            node["boundingVolume"] = {"box": _box(lo, hi)}
            nodes[(tile.level, tile.x, tile.y)] = node
            progress("tiles: 3d", 0.25 + 0.7 * done / total_tiles)
        if level > 0:
            heights = halve_height(heights)
            images = {k: halve_image(v) for k, v in images.items()}
    writer.wait()
    root = nodes.pop((0, 0, 0))
    lo, hi = root.pop("_lo"), root.pop("_hi")
    matrix = _root_matrix_or(root_matrix, lo, hi)
    root["transform"] = [float(v) for v in np.asarray(matrix, float).T.reshape(-1)]
    n_3d = sum(1 for _ in (tmp / "3d").rglob("*.glb"))
    tileset = {
        "asset": {
            "version": "1.1",
            "generator": "Digital Hammurabi worker.tiles",
            "extras": {
                "frame": "root.transform takes the scan frame (mm, SCAN_BUNDLE.md) to glTF "
                "metres, +Y up, as model.glb's root node; boxes and content are in scan mm",
            },
        },
        "geometricError": float(np.linalg.norm(hi - lo)) / 1000.0,
        "root": root,
    }
    (tmp / "3d" / "tileset.json").write_text(json.dumps(tileset), encoding="utf-8")

    # 4. The per-file index (for the API) and index.json, last.
    _fsync_tree_files(tmp / "iiif")
    total_bytes = write_file_list(tmp)
    index = {
        "version": 1,
        "width_px": W,
        "height_px": H,
        "pixel_size_um": pixel_size_um,
        "iiif": {
            "albedo": "iiif/albedo/info.json",
            "normals": "iiif/normals/info.json",
            "height": "iiif/height/info.json",
        },
        "tileset": "3d/tileset.json",
        "height_raw": {
            "path": "height.f32",
            "dtype": "<f4",
            "shape": [H, W],
            "order": "row-major",
            "nodata": "NaN",
            "unit": "um",
        },
        "height_png": {"offset_um": offset_um, "scale_um": scale_um, "nodata_value": 0},
        "files": "files.json",
        "stats": {
            "seconds": round(time.perf_counter() - t_start, 3),
            "bytes": total_bytes,
            "tiles_3d": n_3d,
            "tiles_iiif": n_iiif,
            "levels": levels,
        },
    }
    write_file_atomic(tmp / "index.json", json.dumps(index, indent=1).encode())
    progress("tiles: done", 1.0)
    return index


def _root_matrix_or(matrix, lo, hi) -> np.ndarray:
    return np.asarray(matrix, float) if matrix is not None else gltf_root_matrix(lo, hi)


def _skirt_mm(level_h: np.ndarray, texels, spacing_mm: float) -> float:
    """Skirt depth: the tile's height range, at least one and at most four mesh spacings."""
    tx0, ty0, tx1, ty1 = texels
    region = level_h[ty0:ty1, tx0:tx1]
    finite = region[np.isfinite(region)]
    ptp_mm = float(finite.max() - finite.min()) / 1000.0 if finite.size else 0.0
    return min(4.0 * spacing_mm, max(spacing_mm, ptp_mm))


def build_tiles(model_dir: str | os.PathLike, *, progress: Progress | None = None) -> dict:
    """Build `model_dir/tiles/` (replacing an old one only once the new one is whole);
    returns index.json's dict and records its stats under report.json's "tiles"."""
    model_dir = Path(model_dir)
    progress = progress or (lambda stage, fraction: None)
    try:
        report = json.loads((model_dir / "report.json").read_text(encoding="utf-8"))
        pixel_size_um = float(report["pixel_size_um"])
        height_um = np.load(model_dir / "height.npy", mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TileError(f"model directory {model_dir}: {exc}") from None
    if height_um.ndim != 2:
        raise TileError(f"{model_dir}/height.npy: expected (H, W), got {height_um.shape}")
    albedo = _read_grey_or_rgb(model_dir / "albedo.png", rgb=True)
    normals = _read_grey_or_rgb(model_dir / "normals.png", rgb=True)
    curvature = _read_grey_or_rgb(model_dir / "curvature.png", rgb=False)
    access = _read_grey_or_rgb(model_dir / "accessibility.png", rgb=False)
    written: dict = {}

    def fill(tmp: Path) -> None:
        written["index"] = fill_tiles(
            tmp,
            height_um=height_um,
            albedo=albedo,
            normals_rgb8=normals,
            curvature8=curvature,
            accessibility8=access,
            pixel_size_um=pixel_size_um,
            root_matrix=glb_root_matrix(model_dir / "model.glb"),
            albedo_path=model_dir / "albedo.png",
            normals_path=model_dir / "normals.png",
            gloss=read_gloss(model_dir),
            progress=progress,
        )

    replace_dir_atomic(model_dir / "tiles", fill)
    index = written["index"]
    report["tiles"] = dict(index["stats"])
    write_file_atomic(
        model_dir / "report.json", json.dumps(report, indent=1, allow_nan=False).encode()
    )
    return index
