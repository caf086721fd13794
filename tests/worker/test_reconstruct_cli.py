"""`python -m worker.reconstruct` and the model directory it writes (SCAN_BUNDLE.md)."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh
from PIL import Image

from worker.pipeline import ReconstructionError, reconstruct_bundle
from worker.reconstruct import main
from worker.simulate import simulate_scan

SIZE = (64, 48)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli_sim")
    simulate_scan(out, seed=5, preset="quick", noise="default", size=SIZE)
    return out


def _image(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


def _subset(sim: Path, dest: Path, keep) -> Path:
    """A copy of the simulated bundle whose manifest keeps only the frames `keep` accepts."""
    shutil.copytree(sim / "bundle", dest)
    man = json.loads((dest / "manifest.json").read_text())
    man["frames"] = [f for f in man["frames"] if keep(f)]
    (dest / "manifest.json").write_text(json.dumps(man))
    return dest


def test_model_directory_follows_the_spec(sim, tmp_path, capsys):
    out = tmp_path / "model"
    assert main([str(sim / "bundle"), str(out), "--quiet"]) == 0
    w, h = SIZE
    height = np.load(out / "height.npy")
    normals = np.load(out / "normals.npy")
    assert height.dtype == np.float32 and height.shape == (h, w)
    assert normals.dtype == np.float32 and normals.shape == (h, w, 3)
    mask_png = _image(out / "mask.png")
    assert mask_png.dtype == np.uint8 and set(np.unique(mask_png)) <= {0, 255}
    mask = mask_png == 255
    assert mask.sum() > 0.3 * mask.size
    assert np.all(np.isnan(height[~mask])) and np.all(np.isfinite(height[mask]))
    assert np.all(np.isnan(normals[~mask]))
    np.testing.assert_allclose(np.linalg.norm(normals[mask], axis=-1), 1, atol=1e-4)
    assert np.all(normals[mask][:, 2] < 0)
    assert _image(out / "albedo.png").shape == (h, w, 3)
    assert _image(out / "normals.png").shape == (h, w, 3)

    ply = trimesh.load(out / "mesh.ply", process=False)
    r, c = np.nonzero(mask)
    s_um = json.loads((out / "report.json").read_text())["pixel_size_um"]
    # Vertex (c·s, r·s, −h)/1000 for pixel (r, c), row-major order over the mask.
    np.testing.assert_allclose(
        ply.vertices, np.stack([c * s_um, r * s_um, -height[r, c]], 1) / 1000, rtol=1e-5, atol=1e-7
    )
    assert np.mean(ply.face_normals[:, 2] < 0) > 0.99  # toward the camera (walls may tip)
    gltf = pygltflib.GLTF2.load(str(out / "model.glb"))
    assert gltf.materials[0].normalTexture is not None

    report = json.loads((out / "report.json").read_text())
    assert report["image_size"] == {"width": w, "height": h}
    assert report["used"]["frames"]["photometric"] == 8
    assert report["used"]["fringe_sets"] == 40
    for stage in ("photometric", "fringe", "color", "mask", "fusion", "write", "total"):
        assert report["timings_s"][stage] >= 0
    for key in ("coverage", "median_residual", "median_modulation", "median_abs_disagreement_um"):
        assert report["quality"][key] is not None
    for name in (
        "photometric_residual",
        "lights_used",
        "fringe_modulation",
        "fringe_disagreement_um",
    ):
        assert np.load(out / "quality" / f"{name}.npy").shape == (h, w)
    assert json.loads(capsys.readouterr().out)["surface"] == "default"


def test_photometric_only_bundle_gives_an_integrated_surface(sim, tmp_path):
    bundle = _subset(sim, tmp_path / "photo", lambda f: f["kind"] in ("photometric", "dark"))
    stages = []
    report = reconstruct_bundle(bundle, tmp_path / "m", progress=lambda s, f: stages.append((s, f)))
    assert report["surface"] == "normals"
    assert "fringe_sets" not in report["used"]
    fractions = [f for _, f in stages]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    h = np.load(tmp_path / "m" / "height.npy")
    assert np.isfinite(h).sum() > 0.3 * h.size


def test_fringe_only_bundle_gives_heights_and_warns(sim, tmp_path):
    bundle = _subset(sim, tmp_path / "fringe", lambda f: f["kind"] in ("fringe", "dark"))
    report = reconstruct_bundle(bundle, tmp_path / "m")
    assert report["surface"] == "fringe"
    n = np.load(tmp_path / "m" / "normals.npy")
    assert np.isfinite(n).all(axis=-1).sum() > 0.3 * n.shape[0] * n.shape[1]


def test_fringes_without_references_are_reported(sim, tmp_path):
    bundle = _subset(
        sim,
        tmp_path / "noref",
        lambda f: f["kind"] in ("photometric", "fringe") and f.get("target") != "reference",
    )
    report = reconstruct_bundle(bundle, tmp_path / "m")
    assert any(w.startswith("fringe:") and "no reference frames" in w for w in report["warnings"])
    assert any(
        w.startswith("photometric:") and "uniform illumination" in w for w in report["warnings"]
    )
    assert report["surface"] == "normals"


def test_unusable_bundle_exits_2_and_writes_nothing(sim, tmp_path):
    bundle = _subset(sim, tmp_path / "dark", lambda f: f["kind"] == "dark")
    out = tmp_path / "out"
    with pytest.raises(ReconstructionError, match="nothing to reconstruct"):
        reconstruct_bundle(bundle, out)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["dark"]
    proc = subprocess.run(
        [sys.executable, "-m", "worker.reconstruct", str(bundle), str(out), "--quiet"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
        timeout=120,
    )
    assert proc.returncode == 2
    assert "nothing to reconstruct" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()


def test_invalid_bundle_exits_2_naming_the_problem(tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "manifest.json").write_text('{"format": "cuneiform-scan", "version": 1}')
    assert main([str(bad), str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "invalid scan bundle" in err and "camera" in err
    assert not (tmp_path / "out").exists()


def test_paper_fusion_replaces_an_existing_model(sim, tmp_path):
    out = tmp_path / "model"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    report = reconstruct_bundle(sim / "bundle", out, fusion="paper")
    assert report["surface"] == "paper"
    assert not (out / "stale.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]
    data = (out / "model.glb").read_bytes()
    assert trimesh.load(io.BytesIO(data), file_type="glb").geometry


def test_undecodable_colour_frame_is_named_and_nothing_is_written(sim, tmp_path):
    # The colour frames are decoded in the background, beside the fusion: a frame that
    # fails there is reported like any other (its file named), with OUTDIR untouched.
    bundle = _subset(sim, tmp_path / "bundle", lambda f: True)
    man = json.loads((bundle / "manifest.json").read_text())
    colour = next(f for f in man["frames"] if f["kind"] == "color" and f["target"] == "object")
    png = bundle / colour["file"]
    png.write_bytes(png.read_bytes()[:120])  # the header survives, the pixels do not
    out = tmp_path / "out"
    with pytest.raises(ReconstructionError, match=colour["file"]):
        reconstruct_bundle(bundle, out)
    assert not out.exists()
