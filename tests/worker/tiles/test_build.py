"""`tiles/` of a model directory: the 3D Tiles tileset, the IIIF pyramids, the raw heights.

The 3D Tiles validator is not in the npm registry (`3d-tiles-validator` 404s; it installs
from its repository only), so the tileset is checked structurally here: every bounding box
contains its children's boxes and its content's vertices, geometric errors decrease, every
content URI exists and decodes. The tiles' GLBs go through the Khronos glTF validator and
their meshopt streams through meshoptimizer's own JavaScript decoder.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pygltflib
import pytest

from worker.tiles import TileError, build_tiles
from worker.tiles.__main__ import main as tiles_main
from worker.tiles.build import glb_root_matrix

FRONTEND = Path(__file__).resolve().parents[3] / "frontend"


def _box_corners(box: list[float]) -> np.ndarray:
    c = np.array(box[:3])
    axes = np.array(box[3:]).reshape(3, 3)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    return c + signs @ axes


def _inside(points: np.ndarray, box: list[float], tol: float = 1e-4) -> bool:
    c = np.array(box[:3])
    axes = np.array(box[3:]).reshape(3, 3)
    local = (points - c) @ np.linalg.inv(axes)  # rows are half-axes: coordinates in [-1, 1]
    return bool(np.all(np.abs(local) <= 1 + tol))


def _walk(tile: dict, depth: int = 0):
    yield tile, depth
    for kid in tile.get("children", []):
        yield from _walk(kid, depth + 1)


def _decode(paths: list[Path]) -> list[dict]:
    run = subprocess.run(
        ["node", "scripts/decode-meshopt-glb.mjs", *map(str, paths)],
        cwd=FRONTEND,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_index_json_follows_the_contract(tiled_face):
    model_dir, index, _ = tiled_face
    on_disk = json.loads((model_dir / "tiles" / "index.json").read_text())
    assert on_disk == index
    assert index["version"] == 1
    assert (index["width_px"], index["height_px"]) == (1180, 900)
    assert index["tileset"] == "3d/tileset.json"
    for layer in ("albedo", "normals", "height"):
        assert (model_dir / "tiles" / index["iiif"][layer]).is_file()
    stats = index["stats"]
    assert stats["levels"] == 3 and stats["tiles_3d"] >= 7 and stats["tiles_iiif"] > 3 * 6
    assert stats["bytes"] > 0 and stats["seconds"] > 0
    report = json.loads((model_dir / "report.json").read_text())
    assert report["tiles"] == stats


def test_raw_heights_are_the_model_heights(tiled_face):
    model_dir, index, _ = tiled_face
    raw = index["height_raw"]
    data = np.fromfile(model_dir / "tiles" / raw["path"], dtype=raw["dtype"]).reshape(raw["shape"])
    np.testing.assert_array_equal(data, np.load(model_dir / "height.npy"))


def test_progress_is_reported_in_order(tiled_face):
    _, _, reports = tiled_face
    fractions = [f for _, f in reports]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert {s for s, _ in reports} >= {"tiles: iiif", "tiles: 3d", "tiles: done"}


def test_tileset_structure(tiled_face):
    model_dir, _, _ = tiled_face
    tileset_path = model_dir / "tiles" / "3d" / "tileset.json"
    tileset = json.loads(tileset_path.read_text())
    assert tileset["asset"]["version"] == "1.1"
    root = tileset["root"]
    assert tileset["geometricError"] > root["geometricError"]
    # root.transform is model.glb's scan → glTF root matrix (column-major).
    expected = glb_root_matrix(model_dir / "model.glb")
    np.testing.assert_allclose(np.array(root["transform"]).reshape(4, 4).T, expected)
    contents = []
    for tile, _depth in _walk(root):
        assert tile["refine"] == "REPLACE"
        for kid in tile.get("children", []):
            assert kid["geometricError"] < tile["geometricError"]
            assert _inside(
                _box_corners(kid["boundingVolume"]["box"]), tile["boundingVolume"]["box"]
            )
            info, kinfo = tile["extras"]["dh_tile"], kid["extras"]["dh_tile"]
            assert kinfo["level"] == info["level"] + 1
            assert kinfo["pixel_step"] * 2 == info["pixel_step"]
        if "content" in tile:
            path = tileset_path.parent / tile["content"]["uri"]
            assert path.is_file()
            contents.append((tile, path))
    levels = {t["extras"]["dh_tile"]["level"] for t, _ in contents}
    assert levels == {0, 1, 2}
    leaves = [t for t, _ in contents if t["extras"]["dh_tile"]["level"] == 2]
    assert all(t["extras"]["dh_tile"]["pixel_step"] == 1 for t in leaves)
    # Decoded with meshoptimizer's decoder: content vertices inside their tile's box.
    decoded = _decode([p for _, p in contents])
    for (tile, _), glb in zip(contents, decoded, strict=True):
        pos = np.array(glb["accessors"][0]["values"]).reshape(-1, 3)
        idx = np.array(glb["accessors"][3]["values"])
        assert np.isfinite(pos).all() and idx.max() < len(pos) and len(idx) % 3 == 0
        assert _inside(pos, tile["boundingVolume"]["box"])
        x0, y0, x1, y1 = tile["extras"]["dh_tile"]["px_rect"]
        px_mm = 26.8e-3
        surface = pos[pos[:, 2] <= pos[:, 2].min() + 1.0]
        assert surface[:, 0].min() >= x0 * px_mm - 1e-3
        assert surface[:, 0].max() <= x1 * px_mm + tile["extras"]["dh_tile"]["pixel_step"] * 0.2


def test_leaf_tiles_match_the_model_heights(tiled_face):
    """Surface vertices of a full-resolution tile lie on the model's height map."""
    model_dir, _, _ = tiled_face
    height = np.load(model_dir / "height.npy")
    [glb] = _decode([model_dir / "tiles" / "3d" / "2" / "1_1.glb"])
    pos = np.array(glb["accessors"][0]["values"]).reshape(-1, 3)
    px_mm = 26.8e-3
    cols = np.rint(pos[:, 0] / px_mm).astype(int)
    rows = np.rint(pos[:, 1] / px_mm).astype(int)
    expected_z = -height[rows, cols] / 1000.0
    on_surface = np.isclose(pos[:, 2], expected_z, atol=1e-4)
    assert on_surface.mean() > 0.9  # the rest are the skirt's vertices
    assert np.all(pos[~on_surface, 2] > expected_z[~on_surface])  # skirts hang behind


def test_glb_tiles_pass_the_khronos_validator_and_carry_the_maps(tiled_face):
    model_dir, _, _ = tiled_face
    paths = sorted((model_dir / "tiles" / "3d").rglob("*.glb"))
    run = subprocess.run(
        ["node", "scripts/validate-gltf.mjs", *map(str, paths)],
        cwd=FRONTEND,
        capture_output=True,
        text=True,
        timeout=300,
    )
    reports = json.loads(run.stdout)
    assert run.returncode == 0, [r["issues"]["messages"][:5] for r in reports]
    for r in reports:
        assert r["issues"]["numErrors"] == 0 and r["issues"]["numWarnings"] == 0, r["file"]
    gltf = pygltflib.GLTF2().load(str(paths[0]))
    assert gltf.extensionsRequired == ["EXT_meshopt_compression"]
    maps = gltf.materials[0].extras["dh_maps"]
    assert set(maps) == {"normals", "curvature", "accessibility"}
    assert [gltf.images[gltf.textures[i].source].name for i in maps.values()] == list(maps)
    assert gltf.images[gltf.textures[maps["normals"]].source].mimeType == "image/png"
    assert gltf.scenes[0].extras["dh_tile"]["px_rect"]


def test_leaf_normal_texture_is_the_lossless_full_resolution_normal_map(tiled_face):
    model_dir, _, _ = tiled_face
    path = model_dir / "tiles" / "3d" / "2" / "1_0.glb"
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    image = gltf.images[gltf.textures[gltf.materials[0].extras["dh_maps"]["normals"]].source]
    view = gltf.bufferViews[image.bufferView]
    png = blob[view.byteOffset : view.byteOffset + view.byteLength]
    tex = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    full = cv2.imread(str(model_dir / "normals.png"), cv2.IMREAD_COLOR)[..., ::-1]
    x0, y0, x1, y1 = gltf.scenes[0].extras["dh_tile"]["px_rect"]
    np.testing.assert_array_equal(tex, full[y0:y1, x0:x1])


def test_iiif_info_json_is_valid_and_every_tile_exists(tiled_face):
    model_dir, index, _ = tiled_face
    for layer, rel in index["iiif"].items():
        info_path = model_dir / "tiles" / rel
        info = json.loads(info_path.read_text())
        assert info["@context"] == "http://iiif.io/api/image/3/context.json"
        assert info["type"] == "ImageService3" and info["protocol"] == "http://iiif.io/api/image"
        assert info["profile"] == "level0"
        assert info["id"].endswith(f"/{layer}")
        assert (info["width"], info["height"]) == (1180, 900)
        [tiles] = info["tiles"]
        size = tiles["width"]
        assert tiles.get("height", size) == size
        ext = "jpg" if layer == "albedo" else "png"
        for sf in tiles["scaleFactors"]:
            region = size * sf
            for y in range(0, info["height"], region):
                for x in range(0, info["width"], region):
                    w, h = min(region, info["width"] - x), min(region, info["height"] - y)
                    full = (x, y, w, h) == (0, 0, info["width"], info["height"])
                    name = "full" if full else f"{x},{y},{w},{h}"
                    out = f"{-(-w // sf)},{-(-h // sf)}"
                    tile = info_path.parent / name / out / "0" / f"default.{ext}"
                    if not tile.is_file() and full:
                        tile = info_path.parent / f"{x},{y},{w},{h}" / out / "0" / f"default.{ext}"
                    assert tile.is_file(), tile
        for s in info["sizes"]:
            assert (info_path.parent / "full" / f"{s['width']},{s['height']}").is_dir()
    # The height layer: 16-bit grey, decoded with index.json's mapping.
    mapping = index["height_png"]
    png = next((model_dir / "tiles" / "iiif" / "height").glob("0,0,512,512/512,512/0/*.png"))
    v = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert v.dtype == np.uint16
    height = np.load(model_dir / "height.npy")[:512, :512]
    ok = v > 0
    np.testing.assert_array_equal(ok, np.isfinite(height))
    np.testing.assert_allclose(
        mapping["offset_um"] + mapping["scale_um"] * v[ok], height[ok], atol=mapping["scale_um"]
    )


def test_files_index_lists_every_file_with_its_hash(tiled_face):
    import hashlib

    model_dir, _, _ = tiled_face
    tiles = model_dir / "tiles"
    files = json.loads((tiles / "files.json").read_text())
    on_disk = {
        p.relative_to(tiles).as_posix()
        for p in tiles.rglob("*")
        if p.is_file() and p.name not in ("files.json", "index.json")
    }
    assert set(files) == on_disk
    name = "3d/tileset.json"
    assert files[name]["sha256"] == hashlib.sha256((tiles / name).read_bytes()).hexdigest()
    assert not list(model_dir.glob(".tiles*"))  # no temporary folder left


def test_bad_model_directory_is_a_clear_error_and_writes_nothing(tmp_path, capsys):
    (tmp_path / "report.json").write_text('{"pixel_size_um": 26.8}')
    np.save(tmp_path / "height.npy", np.zeros((20, 20), np.float32))
    with pytest.raises(TileError, match="albedo.png is missing"):
        build_tiles(tmp_path)
    assert tiles_main([str(tmp_path)]) == 2
    assert "albedo.png is missing" in capsys.readouterr().err
    assert not (tmp_path / "tiles").exists()
    assert tiles_main([str(tmp_path / "nowhere")]) == 2


def test_the_manifests_full_size_rule_matches_the_pyramid_on_disk(tiled_face):
    from backend.iiif import IIIF_TILE_PX, level0_full_size
    from worker.tiles.iiif import TILE_PX

    model_dir, index, _ = tiled_face
    assert IIIF_TILE_PX == TILE_PX
    w, h = level0_full_size(index["width_px"], index["height_px"])
    for layer in ("albedo", "normals", "height"):
        assert (model_dir / "tiles" / "iiif" / layer / "full" / f"{w},{h}").is_dir()
