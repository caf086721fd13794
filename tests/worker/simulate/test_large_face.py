"""worker.simulate.large_face: a procedural face written straight to a model directory."""

from __future__ import annotations

import json

import cv2
import numpy as np

from worker.simulate.large_face import PIXEL_SIZE_UM, large_face_height_um, main


def test_cli_writes_a_model_directory(tmp_path, capsys):
    out = tmp_path / "face"
    assert main(["--out", str(out), "--width", "400", "--height", "300", "--seed", "2"]) == 0
    assert "400 × 300 px" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["pixel_size_um"] == PIXEL_SIZE_UM and report["simulated"] is True
    assert report["image_size"] == {"width": 400, "height": 300}
    h = np.load(out / "height.npy")
    n = np.load(out / "normals.npy")
    assert h.shape == (300, 400) and h.dtype == np.float32 and n.shape == (300, 400, 3)
    inside = np.isfinite(h)
    assert 0.8 < inside.mean() < 0.97  # the cushion outline
    np.testing.assert_allclose(np.linalg.norm(n[inside], axis=1), 1.0, atol=1e-5)
    assert (n[inside][:, 2] < 0).all()  # facing the camera (−z)
    mask = cv2.imread(str(out / "mask.png"), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(mask > 127, inside)
    for name in ("albedo.png", "normals.png", "curvature.png", "accessibility.png", "model.glb"):
        assert (out / name).stat().st_size > 0, name


def test_wedges_cut_into_the_dome():
    h = large_face_height_um(600, 400, seed=0)
    smooth = cv2.GaussianBlur(np.nan_to_num(h, nan=0.0), (0, 0), 25)
    dips = (smooth - np.nan_to_num(h, nan=0.0))[np.isfinite(h)]
    assert dips.max() > 50.0  # wedges tens of µm deep and more
    assert (dips > 20.0).mean() > 0.005


def test_a_too_small_face_is_refused(tmp_path, capsys):
    assert main(["--out", str(tmp_path / "x"), "--width", "8", "--height", "8"]) == 2
    assert "at least 16" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
