"""A registered whole tablet's tiles carry what its single-mesh model draws (issue 17): each
face's tiles are made from the normals blended across the seams with the face's weight in
alpha (faces/<label>/normals.png) and from the blended albedo (model.glb's node texture), so
the streamed tablet picks, where faces overlap, the face of larger weight as model.glb does."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pygltflib
import pytest

from worker.assets import derive_assets
from worker.register.io import face_asset_dir, load_model_dir, write_output_dir
from worker.register.run import whole_tablet_model
from worker.tiles.tablet import blended_maps, build_tablet_tiles, glb_node_albedos

HERE = Path(__file__).resolve()


def _write_gt_model_dirs(out: Path):
    sys.path.insert(0, str(HERE.parents[1] / "register"))
    try:
        from synthetic import write_gt_model_dirs
    finally:
        sys.path.pop(0)
    return write_gt_model_dirs(out, size=(96, 80), faces=["obverse", "top", "reverse"])


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """(whole-tablet model dir, {folder: (face dir, transform)}, labels) with its tiles."""
    tmp = tmp_path_factory.mktemp("whole_blended")
    paths, truths = _write_gt_model_dirs(tmp / "faces")
    for p in paths:
        derive_assets(p)
    # The obverse's scan measured gloss (worker/photos.py's files): red = 255·k_s/scale.
    h, w = np.load(paths[0] / "height.npy").shape
    gloss = np.zeros((h, w, 3), np.uint8)
    gloss[..., 0] = np.random.default_rng(1).integers(0, 256, (h, w))
    cv2.imwrite(str(paths[0] / "gloss.png"), gloss[..., ::-1])
    (paths[0] / "gloss.json").write_text('{"strength_scale": 0.3, "exponent": 40.0}')
    loaded = [load_model_dir(p) for p in paths]
    out = write_output_dir(tmp / "model", whole_tablet_model(loaded, truths))
    labels = [c.label for c, _ in loaded]
    faces = {
        face_asset_dir(lab): (Path(p), np.asarray(t, float))
        for lab, p, t in zip(labels, paths, truths, strict=True)
    }
    build_tablet_tiles(out, faces)
    return out, faces, labels


def _tile_images(glb: Path) -> tuple[dict[str, np.ndarray], dict]:
    """A tile GLB's images by name (RGB[A] or grey, as stored) and its material's extras."""
    gltf = pygltflib.GLTF2().load(str(glb))
    blob = gltf.binary_blob()
    out = {}
    for image in gltf.images:
        view = gltf.bufferViews[image.bufferView]
        data = np.frombuffer(blob[view.byteOffset : view.byteOffset + view.byteLength], np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img.ndim == 3:
            img = img[..., [2, 1, 0, 3][: img.shape[2]]]
        out[image.name] = img
    return out, gltf.materials[0].extras


def _finest_tile(tiles: Path, folder: str) -> tuple[Path, list[int]]:
    """The GLB of the face's finest tile (0, 0) and its px_rect (pixel_step 1: its texels
    are the face's pixels)."""
    tileset = json.loads((tiles / folder / "3d" / "tileset.json").read_text())
    node = tileset["root"]
    while node.get("children"):
        node = node["children"][0]
    info = node["extras"]["dh_tile"]
    assert info["pixel_step"] == 1, info
    return tiles / folder / "3d" / node["content"]["uri"], info["px_rect"]


def test_each_faces_tiles_carry_the_blended_normals_and_the_face_weight(whole):
    out, faces, _ = whole
    for folder in faces:
        rgba = cv2.imread(str(out / folder / "normals.png"), cv2.IMREAD_UNCHANGED)
        rgba = rgba[..., [2, 1, 0, 3]]
        glb, (x0, y0, x1, y1) = _finest_tile(out / "tiles", folder)
        images, extras = _tile_images(glb)
        normals = images["normals"]
        assert normals.shape[2] == 4, f"{folder}: the tile's normals have no weight channel"
        np.testing.assert_array_equal(normals, rgba[y0:y1, x0:x1])
        alpha = normals[..., 3]
        # The weight is a weight: 0 off the face and at its rim, 255 well inside.
        assert alpha.min() == 0 and alpha.max() == 255, (folder, alpha.min(), alpha.max())
        assert "normals" in extras["dh_maps"]


def test_each_faces_tiles_carry_the_blended_albedo_of_model_glb(whole):
    out, faces, labels = whole
    albedos = glb_node_albedos(out / "model.glb")
    assert set(albedos) == {face_asset_dir(lab) for lab in labels}
    for folder, (face_dir, _) in faces.items():
        glb, (x0, y0, x1, y1) = _finest_tile(out / "tiles", folder)
        tile_albedo = _tile_images(glb)[0]["albedo"].astype(int)  # JPEG, quality 90
        blended = albedos[folder][y0:y1, x0:x1].astype(int)
        own = cv2.imread(str(face_dir / "albedo.png"))[..., ::-1][y0:y1, x0:x1].astype(int)
        assert np.abs(tile_albedo - blended).mean() < 4.0, folder
        if np.abs(blended - own).mean() > 1.0:  # where blending changed it, the tile follows
            assert np.abs(tile_albedo - blended).mean() < np.abs(tile_albedo - own).mean()


def test_the_iiif_normals_stay_rgb_and_faces_without_blended_maps_use_their_own(whole, tmp_path):
    out, faces, _ = whole
    folder = next(iter(faces))
    info = json.loads((out / "tiles" / folder / "iiif" / "normals" / "info.json").read_text())
    full = next((out / "tiles" / folder / "iiif" / "normals" / "full").glob("*/0/default.png"))
    assert info["width"] > 0 and cv2.imread(str(full), cv2.IMREAD_UNCHANGED).shape[2] == 3
    # A folder the model has no maps for: nothing blended (its own normals, RGB, are tiled).
    assert blended_maps(tmp_path, folder) == {}


def test_a_face_with_measured_gloss_tiles_it_and_one_without_does_not(whole):
    out, faces, _ = whole
    (obverse, (face_dir, _)), (other, _) = list(faces.items())[:2]
    red = cv2.imread(str(face_dir / "gloss.png"))[..., 2]
    glb, (x0, y0, x1, y1) = _finest_tile(out / "tiles", obverse)
    images, extras = _tile_images(glb)
    np.testing.assert_array_equal(images["gloss"], red[y0:y1, x0:x1])
    assert extras["dh_gloss"] == {"strength_scale": 0.3, "exponent": 40.0}
    assert extras["dh_maps"]["gloss"] == 4
    images, extras = _tile_images(_finest_tile(out / "tiles", other)[0])
    assert "gloss" not in images and "gloss" not in extras["dh_maps"] and "dh_gloss" not in extras
