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


def _add_photos(d: Path, k: int) -> dict[str, bytes]:
    """A face model's photographs and gloss as worker/photos.py writes them (small stand-ins)."""
    (d / "photos").mkdir()
    files = {
        f"photos/000-photometric-az{k:05.1f}.jpg": b"\xff\xd8 face %d light 0" % k,
        f"photos/001-color-az{k:05.1f}.jpg": b"\xff\xd8 face %d light 1" % k,
        "gloss.png": b"\x89PNG gloss of face %d" % k,
        "gloss.json": json.dumps({"strength_scale": 0.5, "exponent": 30 + k}).encode(),
    }
    entries = [
        {"file": n, "kind": "photometric", "light": [0, 0, -1]} for n in files if "photos/" in n
    ]
    files["photos/index.json"] = json.dumps({"version": 1, "photos": entries}).encode()
    for name, data in files.items():
        (d / name).write_bytes(data)
    return files


def test_each_face_carries_its_photographs_and_gloss(gt, tmp_path):
    import shutil

    paths, truths = gt
    copies, expected = [], {}
    for k, path in enumerate(paths):
        d = Path(shutil.copytree(path, tmp_path / path.name))
        copies.append(d)
        expected[path.name] = _add_photos(d, k) if k % 2 == 0 else {}
    loaded = [load_model_dir(p) for p in copies]
    files = whole_tablet_model(loaded, truths)
    for cloud, _ in loaded:
        prefix = face_asset_dir(cloud.label)
        got = {
            n.removeprefix(f"{prefix}/"): files[n]
            for n in files
            if n.startswith(f"{prefix}/photos/") or n.startswith(f"{prefix}/gloss.")
        }
        assert got == expected[cloud.face], cloud.label


@pytest.mark.parametrize(
    "bad",
    ["../../report.json", "photos/../height.npy", "/etc/passwd", "photos/a.png", None],
)
def test_a_photo_index_naming_a_file_out_of_photos_is_never_followed(gt, tmp_path, bad, caplog):
    import shutil

    paths, _ = gt
    d = Path(shutil.copytree(paths[0], tmp_path / paths[0].name))
    files = _add_photos(d, 0)
    index = json.loads(files["photos/index.json"])
    index["photos"].append({"file": bad, "light": [0, 0, -1]})
    (d / "photos" / "index.json").write_text(json.dumps(index))
    _, raw = load_model_dir(d)
    # The gloss still comes; the photographs do not, not even those the index named rightly.
    assert sorted(raw["photo_files"]) == ["gloss.json", "gloss.png"]
    assert "photographs left out" in caplog.text and "photos[2].file" in caplog.text


def test_a_photo_the_index_lists_but_the_model_lacks_leaves_the_photographs_out(gt, tmp_path):
    import shutil

    paths, _ = gt
    d = Path(shutil.copytree(paths[0], tmp_path / paths[0].name))
    files = _add_photos(d, 0)
    (d / next(n for n in files if n.endswith(".jpg"))).unlink()
    _, raw = load_model_dir(d)
    assert sorted(raw["photo_files"]) == ["gloss.json", "gloss.png"]


def test_each_face_carries_its_trust_and_heights_with_one_legend(gt, tmp_path):
    """faces/<label>/trust.png, trust.json and uncertainty_um.npy are the face model's own
    (worker/trust_assets.py on the same maps), encoded on one pair of legend tops for every
    face; its walls map (refinements) is carried and read, and its heights are carried."""
    import shutil

    import cv2

    from worker.trust import DISAGREE, NORMALS_ONLY, REFINED
    from worker.trust_assets import trust_assets

    paths, truths = gt
    copies = []
    for k, path in enumerate(paths):
        d = Path(shutil.copytree(path, tmp_path / path.name))
        (d / "quality").mkdir()
        h = np.load(d / "height.npy")
        rng = np.random.default_rng(k)
        # Fringe noise growing with k (each face its own legend top), no fringe height in
        # the right third, a biased block, and walls a refinement changed.
        dis = rng.normal(0.0, 1.0 + 3.0 * k, h.shape).astype(np.float32)
        dis[:, 2 * h.shape[1] // 3 :] = np.nan
        dis[10:14, 10:14] = 200.0
        walls = np.zeros(h.shape, np.uint8)
        walls[20:23, 5:8] = 1
        np.save(d / "quality" / "fringe_disagreement_um.npy", dis)
        np.save(d / "quality" / "walls.npy", walls)
        copies.append(d)
    loaded = [load_model_dir(p) for p in copies]
    files = whole_tablet_model(loaded, truths)
    metas, own_tops, normals_only = {}, [], 0
    for (cloud, raw), d in zip(loaded, copies, strict=True):
        prefix = face_asset_dir(cloud.label)
        h = np.load(d / "height.npy")
        np.testing.assert_array_equal(np.load(io.BytesIO(files[f"{prefix}/height.npy"])), h)
        own = trust_assets(d, h, json.loads((d / "report.json").read_text()))
        own_meta = json.loads(own["trust.json"])
        own_tops.append((own_meta["disagreement_scale_um"], own_meta["uncertainty_scale_um"]))
        sigma = np.load(io.BytesIO(files[f"{prefix}/uncertainty_um.npy"]))
        np.testing.assert_array_equal(sigma, np.load(io.BytesIO(own["uncertainty_um.npy"])))
        rgba = cv2.imdecode(np.frombuffer(files[f"{prefix}/trust.png"], np.uint8), -1)
        own_rgba = cv2.imdecode(np.frombuffer(own["trust.png"], np.uint8), -1)
        classes = rgba[..., 2]
        np.testing.assert_array_equal(classes, own_rgba[..., 2])
        mask = raw["mask"] & np.isfinite(h)
        assert (classes[10:14, 10:14][mask[10:14, 10:14]] == DISAGREE).all(), cloud.label
        assert (classes[20:23, 5:8][mask[20:23, 5:8]] == REFINED).all(), cloud.label
        right = classes[:, 2 * h.shape[1] // 3 + 2 :]
        assert (right[right > 0] == NORMALS_ONLY).all(), cloud.label  # no fringe height
        normals_only += int((right == NORMALS_ONLY).sum())
        metas[cloud.label] = json.loads(files[f"{prefix}/trust.json"])
        # B (σ_h) on the common legend top, not the face's own.
        top = metas[cloud.label]["uncertainty_scale_um"]
        b = np.rint(255 * np.clip(np.nan_to_num(sigma) / top, 0, 1))
        assert np.abs(rgba[..., 0][mask] - b[mask]).max() <= 1, cloud.label
        assert metas[cloud.label]["pixel_size_um"] == raw["pixel_size_um"]
        assert metas[cloud.label]["pixels"] == int(np.isfinite(h).sum())
    tops = {(m["disagreement_scale_um"], m["uncertainty_scale_um"]) for m in metas.values()}
    assert tops == {(max(t[0] for t in own_tops), max(t[1] for t in own_tops))}
    assert len({t[0] for t in own_tops}) > 1  # the faces' own tops differ: one was chosen
    assert normals_only > 0
