"""`python -m worker.register MODEL_DIR... OUTDIR`: outputs and bad input."""

from __future__ import annotations

import io
import json
import shutil

import numpy as np
import pygltflib
import pytest
import trimesh
from PIL import Image

from worker.register.__main__ import main

from .synthetic import write_gt_model_dirs


@pytest.fixture(scope="module")
def model_dirs(tmp_path_factory):
    paths, truths = write_gt_model_dirs(tmp_path_factory.mktemp("reg_cli"), size=(64, 52))
    return paths, truths


@pytest.mark.slow
def test_cli_writes_transforms_meshes_plates_and_report(model_dirs, tmp_path, capsys):
    paths, _ = model_dirs
    out = tmp_path / "out"
    assert main([*map(str, paths), str(out), "--dpi", "150", "--name", "P1"]) == 0
    assert "overlap" in capsys.readouterr().out
    tr = json.loads((out / "transforms.json").read_text())
    assert set(tr["scans"]) == {
        f"sim-0-{f}" for f in ("obverse", "reverse", "top", "bottom", "left", "right")
    }
    for s in tr["scans"].values():
        r = np.array(s["rotation"])
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-6) and len(s["translation_mm"]) == 3
    report = json.loads((out / "report.json").read_text())
    assert report["pairs"] and all(
        p["rms_um"] >= 0 and 0 < p["overlap"] <= 1 for p in report["pairs"]
    )
    assert report["fatcross"]["dpi"] == 150.0
    assert report["simulated"] is False and report["fatcross"]["designation"] == "P1"
    merged = trimesh.load(out / "merged.ply", process=False)
    assert len(merged.faces) > 1000 and merged.visual.vertex_colors.shape[1] == 4
    glb = pygltflib.GLTF2().load_binary(str(out / "tablet.glb"))
    assert {n.name for n in glb.nodes if n.mesh is not None} == set(tr["scans"])
    for suffix in ("o", "r", "te", "be", "le", "re"):
        for kind in ("natural", "curvature"):
            assert (out / "fatcross" / f"P1_{kind}_{suffix}.png").is_file()
    assert (out / "fatcross" / "P1_fatcross.pdf").read_bytes().startswith(b"%PDF")
    # The scans' own normals shade most of every view.
    assert min(report["fatcross"]["normals_from_scans"].values()) > 0.5
    assert report["fatcross"]["curvature_display_per_mm"] > 0  # one range for the plate
    with Image.open(io.BytesIO((out / "fatcross" / "P1_fatcross_natural.png").read_bytes())) as im:
        assert im.text["px_per_mm"] == f"{150 / 25.4:.4f}"
        assert im.text["Title"].startswith("P1") and im.text["Simulated"] == "false"
        assert abs(im.info["dpi"][0] - 150) < 0.5
        assert im.mode == "RGB" and im.size[0] > 50


def test_cli_bad_input_exits_2_with_a_clear_message(model_dirs, tmp_path, capsys):
    paths, _ = model_dirs
    out = tmp_path / "out"
    assert main([str(paths[0]), str(out)]) == 2
    assert "at least two model directories" in capsys.readouterr().err
    assert main([str(paths[0]), str(tmp_path / "nope"), str(out)]) == 2
    assert "nope: not a model directory" in capsys.readouterr().err
    broken = tmp_path / "broken"
    shutil.copytree(paths[1], broken)
    (broken / "report.json").unlink()
    assert main([str(paths[0]), str(broken), str(out)]) == 2
    assert "broken: missing report.json" in capsys.readouterr().err
    full = tmp_path / "full"
    full.mkdir()
    (full / "x").write_text("x")
    assert main([*map(str, paths[:2]), str(full)]) == 2
    assert "not empty" in capsys.readouterr().err
    assert not out.exists()
