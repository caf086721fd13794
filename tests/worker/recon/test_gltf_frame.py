"""model.glb in glTF's convention (SCAN_BUNDLE.md): metres, +Y up, facing +Z, one root node
with the scan frame in its extras; the Khronos glTF validator reports no error."""

from __future__ import annotations

import io
import json
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh

from worker.recon.glb import glb_bytes
from worker.recon.gltf_frame import EXTRAS_KEY
from worker.register.merge import scene_glb

S_UM = 25.0
FRONTEND = Path(__file__).resolve().parents[3] / "frontend"


def _face_glb(rows=40, cols=60):
    y, x = np.mgrid[0:rows, 0:cols]
    # A dome 0.5 mm high toward the camera (h > 0 is toward the camera, i.e. −z).
    r2 = ((x - cols / 2) / cols) ** 2 + ((y - rows / 2) / rows) ** 2
    h = (500.0 * (1 - 4 * r2)).astype(np.float32)
    mask = np.ones((rows, cols), bool)
    n = np.zeros((rows, cols, 3), np.float32)
    n[..., 2] = -1
    albedo = np.full((rows, cols, 3), 120, np.uint8)
    albedo[: rows // 4] = 250  # a bright band along the image's top rows
    data, _ = glb_bytes(h, mask, n, albedo, pixel_size_um=S_UM, max_triangles=2000)
    return data, h


def _world_mesh(data: bytes) -> trimesh.Trimesh:
    scene = trimesh.load(io.BytesIO(data), file_type="glb")
    return scene.to_geometry()  # node transforms applied: glTF's frame


def test_face_glb_is_in_metres_upright_and_faces_plus_z():
    rows, cols = 40, 60
    data, h = _face_glb(rows, cols)
    world = _world_mesh(data)
    ext = world.bounds[1] - world.bounds[0]
    assert ext[0] == pytest.approx((cols - 1) * S_UM * 1e-6, rel=1e-5)  # width in metres
    assert ext[1] == pytest.approx((rows - 1) * S_UM * 1e-6, rel=1e-5)
    # Centred on the origin.
    np.testing.assert_allclose(world.bounds.mean(axis=0), 0, atol=1e-9)
    # The dome rises toward +Z (toward the default glTF camera) and every face looks at it.
    assert np.all(world.face_normals[:, 2] > 0)
    top = world.vertices[:, 2].argmax()
    assert world.vertices[top, 0] == pytest.approx(0, abs=2 * S_UM * 1e-6)
    # Upright: the image's first rows (y small in the scan frame) are at the top (+Y).
    gltf = pygltflib.GLTF2.load_from_bytes(data)
    (root,) = gltf.scenes[gltf.scene].nodes
    m = np.asarray(gltf.nodes[root].matrix).reshape(4, 4).T
    first_row_mm = np.array([0.0, 0.0, 0.0, 1.0])
    last_row_mm = np.array([0.0, (rows - 1) * S_UM / 1000, 0.0, 1.0])
    assert (m @ first_row_mm)[1] > (m @ last_row_mm)[1]


def test_face_glb_root_records_the_scan_frame_and_its_children_stay_in_mm():
    data, _ = _face_glb()
    gltf = pygltflib.GLTF2.load_from_bytes(data)
    (root,) = gltf.scenes[gltf.scene].nodes
    node = gltf.nodes[root]
    frame = node.extras[EXTRAS_KEY]
    assert frame["units"] == "millimetre"
    assert frame["to_gltf_matrix_column_major"] == pytest.approx(node.matrix)
    m = np.asarray(node.matrix).reshape(4, 4).T
    assert np.linalg.det(m[:3, :3]) > 0  # a rotation (and scale): winding kept
    np.testing.assert_allclose(np.abs(np.diag(m[:3, :3])), 1e-3)
    (child,) = node.children
    pos = gltf.accessors[gltf.meshes[gltf.nodes[child].mesh].primitives[0].attributes.POSITION]
    assert pos.max[0] == pytest.approx(59 * S_UM / 1000, rel=1e-6)  # scan-frame mm


def test_whole_tablet_scene_keeps_its_face_nodes_under_one_root():
    box = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    meshes = {"obverse": box.copy(), "reverse": box.copy()}
    shift = np.eye(4)
    shift[2, 3] = 10.0
    data = scene_glb(meshes, {"obverse": np.eye(4), "reverse": shift})
    gltf = pygltflib.GLTF2.load_from_bytes(data)
    (root,) = gltf.scenes[gltf.scene].nodes
    assert EXTRAS_KEY in gltf.nodes[root].extras
    names = {gltf.nodes[i].name for i in range(len(gltf.nodes)) if gltf.nodes[i].mesh is not None}
    assert names == {"obverse", "reverse"}
    world = _world_mesh(data)
    ext = world.bounds[1] - world.bounds[0]
    np.testing.assert_allclose(ext, [0.030, 0.020, 0.020], rtol=1e-6)  # metres
    np.testing.assert_allclose(world.bounds.mean(axis=0), 0, atol=1e-9)


def _khronos(paths: list[Path]) -> list[dict]:
    script = FRONTEND / "scripts" / "validate-gltf.mjs"
    run = subprocess.run(
        ["node", str(script), *map(str, paths)],
        cwd=FRONTEND,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.stdout, run.stderr
    return json.loads(run.stdout)


def test_khronos_validator_reports_no_error_on_face_and_whole_tablet(tmp_path):
    face, _ = _face_glb()
    (tmp_path / "face.glb").write_bytes(face)
    box = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    tablet = scene_glb(
        {"obverse": box, "reverse": box.copy()}, {"obverse": np.eye(4), "reverse": np.eye(4)}
    )
    (tmp_path / "tablet.glb").write_bytes(tablet)
    reports = _khronos([tmp_path / "face.glb", tmp_path / "tablet.glb"])
    for report in reports:
        errors = [m for m in report["issues"]["messages"] if m["severity"] == 0]
        assert report["issues"]["numErrors"] == 0, (report["file"], errors)


def test_khronos_validator_does_catch_a_broken_glb(tmp_path):
    # The check above must be able to fail: an accessor pointing past its buffer view.
    face, _ = _face_glb()
    gltf = pygltflib.GLTF2.load_from_bytes(face)
    gltf.accessors[0].count += 10_000
    (tmp_path / "bad.glb").write_bytes(b"".join(gltf.save_to_bytes()))
    (report,) = _khronos([tmp_path / "bad.glb"])
    assert report["issues"]["numErrors"] > 0
