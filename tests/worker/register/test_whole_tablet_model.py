"""The whole tablet for the viewer (`worker.register.run.whole_tablet_model`): one glTF node
per face with its image grid and albedo, and each face's full-resolution normals with blending
weights, from the simulator's ground truth of six faces at their true poses."""

from __future__ import annotations

import io
import json
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from PIL import Image

from worker.register.io import face_asset_dir, load_model_dir
from worker.register.run import blend_loaded, whole_tablet_model

from .synthetic import write_gt_model_dirs

FRONTEND = Path(__file__).resolve().parents[3] / "frontend"


@pytest.fixture(scope="module")
def gt(tmp_path_factory):
    return write_gt_model_dirs(tmp_path_factory.mktemp("gt"), size=(64, 52))


@pytest.fixture(scope="module")
def model(gt):
    paths, truths = gt
    loaded = [load_model_dir(p) for p in paths]
    return loaded, whole_tablet_model(loaded, truths)


def test_every_face_node_has_its_image_grid_and_albedo(model):
    loaded, files = model
    gltf = pygltflib.GLTF2.load_from_bytes(files["model.glb"])
    nodes = {n.name: n for n in gltf.nodes if n.mesh is not None}
    assert set(nodes) == {c.label for c, _ in loaded}
    for node in nodes.values():
        prim = gltf.meshes[node.mesh].primitives[0]
        assert prim.attributes.TEXCOORD_0 is not None, node.name
        material = gltf.materials[prim.material]
        assert material.pbrMetallicRoughness.baseColorTexture is not None, node.name


def test_every_face_keeps_its_full_resolution_normals_and_weights(model, gt):
    loaded, files = model
    blended = blend_loaded(loaded, gt[1])
    for (cloud, raw), (normals, _) in zip(loaded, blended, strict=True):
        name = f"{face_asset_dir(cloud.label)}/normals.png"
        rgba = np.asarray(Image.open(io.BytesIO(files[name])))
        mask = raw["mask"] & np.all(np.isfinite(raw["normals"]), axis=2)
        assert rgba.shape == (*mask.shape, 4)
        decoded = rgba[..., :3] / 127.5 - 1.0
        # Full resolution: the face's normals blended across the seams, 8-bit quantisation only,
        err = np.abs(decoded[mask] - normals[mask]).max()
        assert err < 1 / 127.5 + 1e-6, (cloud.label, err)
        # and the face's own normals wherever it alone saw the surface (most of it).
        own = np.all(np.abs(decoded - raw["normals"]) < 1 / 127.5 + 1e-6, axis=2)
        assert own[mask].mean() > 0.5, cloud.label
        weight = rgba[..., 3]
        assert weight[~mask].max() == 0
        assert weight[mask].max() > 200  # the face's own centre: facing its camera, far in


def test_khronos_validator_reports_no_error_on_the_whole_tablet(model, tmp_path):
    _, files = model
    (tmp_path / "tablet.glb").write_bytes(files["model.glb"])
    run = subprocess.run(
        ["node", str(FRONTEND / "scripts" / "validate-gltf.mjs"), str(tmp_path / "tablet.glb")],
        cwd=FRONTEND,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.stdout, run.stderr
    (report,) = json.loads(run.stdout)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]


def test_each_face_carries_its_quality_maps_on_its_own_grid(gt, tmp_path):
    import shutil

    paths, truths = gt
    copies, expected = [], {}
    for k, path in enumerate(paths):
        d = Path(shutil.copytree(path, tmp_path / path.name))
        (d / "quality").mkdir()
        h, w = np.load(d / "height.npy").shape
        residual = np.random.default_rng(k).random((h, w)).astype(np.float32)
        np.save(d / "quality" / "photometric_residual.npy", residual)
        np.save(d / "quality" / "guard.npy", np.full((h, w), k, np.uint8))
        (d / "quality" / "notes.txt").write_text("not a quality map")  # left out
        copies.append(d)
        expected[path.name] = residual
    loaded = [load_model_dir(p) for p in copies]
    files = whole_tablet_model(loaded, truths)
    for k, (cloud, _) in enumerate(loaded):
        prefix = f"{face_asset_dir(cloud.label)}/quality"
        assert sorted(n for n in files if n.startswith(prefix)) == [
            f"{prefix}/guard.npy",
            f"{prefix}/photometric_residual.npy",
        ]
        got = np.load(io.BytesIO(files[f"{prefix}/photometric_residual.npy"]))
        np.testing.assert_array_equal(got, expected[cloud.face])
        assert np.load(io.BytesIO(files[f"{prefix}/guard.npy"])).max() == k
