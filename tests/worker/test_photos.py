"""The photo stack and the gloss kept beside a model (worker.photos), on simulated scans."""

import json

import cv2
import numpy as np
import pytest

from worker.photos import main, write_photo_assets
from worker.pipeline import reconstruct_bundle
from worker.simulate import simulate_scan

SIZE = (160, 120)


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """A matte scan (no lobe, no noise) and a glossy dark one (one lobe, k_s 0.2, α 60)."""
    root = tmp_path_factory.mktemp("photos")
    out = {}
    for name, kw in {
        "matte": {"noise": "clean"},
        "glossy": {"noise": "default", "physics": "glossy-dark"},
    }.items():
        simulate_scan(root / name, seed=1, preset="quick", size=SIZE, **kw)
        reconstruct_bundle(root / name / "bundle", root / f"{name}-model")
        out[name] = (root / name / "bundle", root / f"{name}-model")
    return out


def test_every_light_is_kept_as_a_picture_with_its_direction(scans):
    bundle, model = scans["glossy"]
    names = write_photo_assets(bundle, model)
    index = json.loads((model / "photos" / "index.json").read_text())
    manifest = json.loads((bundle / "manifest.json").read_text())
    photometric = [
        f
        for f in manifest["frames"]
        if f["kind"] == "photometric" and f.get("target", "object") == "object"
    ]
    kinds = [p["kind"] for p in index["photos"]]
    assert kinds.count("photometric") == len(photometric)
    assert kinds.count("color") >= 1
    for p in index["photos"]:
        assert p["file"] in names
        light = np.array(p["light"])
        assert abs(np.linalg.norm(light) - 1) < 1e-5 and light[2] < 0  # toward the source
        phi = np.radians(p["azimuth_deg"])
        assert np.allclose(light[:2] / np.hypot(*light[:2]), [np.sin(phi), np.cos(phi)], atol=1e-5)
        img = cv2.imread(str(model / p["file"]), cv2.IMREAD_UNCHANGED)
        assert img.shape[:2] == (index["size_px"][1], index["size_px"][0])
        assert (img.ndim == 3) == (p["kind"] == "color")
    # Slopes facing +x are brighter lit from azimuth 90° (+x) than from 270°, and slopes
    # facing −x the other way round: each picture is its own light's frame.
    by_az = {p["azimuth_deg"]: p for p in index["photos"] if p["kind"] == "photometric"}
    right = cv2.imread(str(model / by_az[90.0]["file"]), cv2.IMREAD_GRAYSCALE).astype(float)
    left = cv2.imread(str(model / by_az[270.0]["file"]), cv2.IMREAD_GRAYSCALE).astype(float)
    normals = np.load(model / "normals.npy")
    facing_right = normals[..., 0] > 0.3  # toward +x, where the azimuth-90° source is
    facing_left = normals[..., 0] < -0.3
    assert (right - left)[facing_right].mean() > 10 > (right - left)[facing_left].mean()


def test_gloss_is_found_on_glossy_clay_and_not_on_matte(scans):
    bundle, model = scans["glossy"]
    write_photo_assets(bundle, model)
    report = json.loads((model / "gloss.json").read_text())
    assert "stood_down" not in report
    assert 16 <= report["exponent"] <= 128
    gloss = cv2.imread(str(model / "gloss.png"))[..., ::-1]
    mask = cv2.imread(str(model / "mask.png"), cv2.IMREAD_GRAYSCALE) == 255
    strength = gloss[..., 0] / 255 * report["strength_scale"]
    assert 0.04 < np.median(strength[mask]) < 0.4  # truth 0.2 (normals' errors bias it low)
    assert not gloss[~mask].any()

    bundle, model = scans["matte"]
    write_photo_assets(bundle, model)
    report = json.loads((model / "gloss.json").read_text())
    assert "stood_down" in report
    assert not (model / "gloss.png").exists()


def test_the_command_line_names_what_is_wrong(tmp_path, capsys):
    assert main([str(tmp_path / "nothing"), str(tmp_path)]) == 2
    assert "mask.png" in capsys.readouterr().err
