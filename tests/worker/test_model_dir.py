"""Model directory writer (worker.model_dir): files, shared textures, atomic replacement."""

import json

import numpy as np
import pygltflib
import pytest

from worker import model_dir
from worker.model_dir import ModelArrays, write_model_dir


def _model(rows=24, cols=32):
    rng = np.random.default_rng(0)
    mask = np.zeros((rows, cols), bool)
    mask[3:-3, 4:-4] = True
    n = np.zeros((rows, cols, 3), np.float32)
    n[..., 2] = -1
    return ModelArrays(
        height_um=rng.normal(0, 10, (rows, cols)).astype(np.float32),
        normals=n,
        albedo_srgb8=rng.integers(0, 256, (rows, cols, 3), dtype=np.uint8),
        mask=mask,
        pixel_size_um=25.0,
        quality={"fringe_modulation": rng.random((rows, cols)).astype(np.float32)},
    )


def test_every_file_is_written_and_the_report_last_sees_the_mesh(tmp_path):
    seen = {}

    def finish(report):
        seen["files"] = sorted(p.name for p in next(tmp_path.glob(".out.tmp-*")).rglob("*"))
        return {**report, "finished": True}

    report = write_model_dir(tmp_path / "out", _model(), {"format": "x"}, finish_report=finish)
    names = {p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*")}
    assert names == {
        "height.npy",
        "normals.npy",
        "albedo.png",
        "mask.png",
        "normals.png",
        "mesh.ply",
        "model.glb",
        "quality",
        "quality/fringe_modulation.npy",
        "report.json",
    }
    assert "report.json" not in seen["files"] and "model.glb" in seen["files"]
    on_disk = json.loads((tmp_path / "out" / "report.json").read_text())
    assert on_disk == report and report["finished"] and report["mesh"]["ply_vertices"] > 0


def test_albedo_png_is_the_glb_base_colour_texture(tmp_path):
    write_model_dir(tmp_path / "out", _model(), {})
    gltf = pygltflib.GLTF2.load(str(tmp_path / "out" / "model.glb"))
    view = gltf.bufferViews[gltf.images[0].bufferView]
    texture = gltf.binary_blob()[view.byteOffset : view.byteOffset + view.byteLength]
    assert texture == (tmp_path / "out" / "albedo.png").read_bytes()


def test_a_failed_write_leaves_the_old_directory(tmp_path, monkeypatch):
    write_model_dir(tmp_path / "out", _model(), {"run": 1})

    def fail(path, data):
        if path.name == "mesh.ply":
            raise OSError("disk full")
        return real(path, data)

    real = model_dir.write_new_file
    monkeypatch.setattr(model_dir, "write_new_file", fail)
    with pytest.raises(OSError, match="disk full"):
        write_model_dir(tmp_path / "out", _model(), {"run": 2})
    assert json.loads((tmp_path / "out" / "report.json").read_text())["run"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
