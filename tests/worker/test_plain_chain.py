"""`--fusion plain` (worker.plain_chain, worker.recon.plain): the textbook floor of issue 14.

Thresholds on the simulated scan were measured at commit time (quick preset, 128×96, seed 5,
`default` noise, 268 µm pixels: fused MAE 4.6 µm, RMS 8.0 µm, normal median 0.77°;
photometric-only normal median 1.8°; fringe-only MAE 4.0 µm) and are asserted with margin.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from worker.recon.evaluate import evaluate
from worker.recon.photometric import light_directions
from worker.recon.plain import (
    average_azimuths_um,
    fringe_weight,
    fuse_plain_um,
    least_squares_normals,
    normals_from_height,
    plain_mask,
)
from worker.reconstruct import main
from worker.simulate import simulate_scan

SIZE = (128, 96)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("plain_sim")
    simulate_scan(out, seed=5, preset="quick", noise="default", size=SIZE)
    return out


def _subset(sim: Path, dest: Path, kinds) -> Path:
    """A copy of the simulated bundle whose manifest keeps only frames of the given kinds."""
    shutil.copytree(sim / "bundle", dest)
    man = json.loads((dest / "manifest.json").read_text())
    man["frames"] = [f for f in man["frames"] if f["kind"] in kinds]
    (dest / "manifest.json").write_text(json.dumps(man))
    return dest


def _figures(sim: Path, model: Path) -> dict:
    gt = {k: np.load(sim / "gt" / f"{k}.npy") for k in ("height", "normals", "mask")}
    wedges = json.loads((sim / "gt" / "wedges.json").read_text())["wedges"]
    with Image.open(model / "mask.png") as im:
        mask = np.asarray(im) == 255
    return evaluate(
        np.load(model / "height.npy"),
        np.load(model / "normals.npy"),
        mask,
        gt_height_um=gt["height"],
        gt_normals=gt["normals"],
        gt_mask=gt["mask"],
        wedges=wedges,
    )


def _run(bundle: Path, out: Path, *extra: str) -> dict:
    assert main([str(bundle), str(out), "--fusion", "plain", "--quiet", *extra]) == 0
    return json.loads((out / "report.json").read_text())


def test_plain_chain_full_bundle(sim, tmp_path):
    out = tmp_path / "model"
    report = _run(sim / "bundle", out)
    assert report["fusion"] == "plain" and report["surface"] == "fused"
    for name in ("height.npy", "normals.npy", "albedo.png", "mask.png", "mesh.ply", "model.glb"):
        assert (out / name).is_file(), name
    h = np.load(out / "height.npy")
    n = np.load(out / "normals.npy")
    with Image.open(out / "mask.png") as im:
        mask = np.asarray(im) == 255
    assert np.all(np.isfinite(h[mask])) and np.all(np.isnan(h[~mask]))
    np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1, atol=1e-4)
    with Image.open(out / "albedo.png") as im:
        assert np.asarray(im).shape == (SIZE[1], SIZE[0], 3)
    f = _figures(sim, out)
    assert f["coverage"] > 0.95
    assert f["height_mae_um"] < 8.0
    assert f["height_rms_um"] < 15.0
    assert f["normal_median_deg"] < 1.2
    assert f["height_out_of_range"] == 0
    assert {"photometric", "fringe", "mask", "fusion", "write", "total"} <= set(report["timings_s"])


def test_plain_chain_photometric_only(sim, tmp_path):
    bundle = _subset(sim, tmp_path / "photo", {"dark", "photometric", "color"})
    report = _run(bundle, tmp_path / "model")
    assert report["surface"] == "normals"
    f = _figures(sim, tmp_path / "model")
    assert f["coverage"] > 0.95
    assert f["normal_median_deg"] < 2.5
    # Least-squares normals are biased (irradiance non-uniformity, gloss): heights integrated
    # from them alone drift by tens of µm over the tablet (measured MAE 41.5 µm).
    assert f["height_mae_um"] < 70.0


def test_plain_chain_fringe_only(sim, tmp_path):
    bundle = _subset(sim, tmp_path / "fringe", {"dark", "fringe"})
    report = _run(bundle, tmp_path / "model")
    assert report["surface"] == "fringe"
    f = _figures(sim, tmp_path / "model")
    assert f["coverage"] > 0.8
    assert f["height_mae_um"] < 7.0
    assert f["normal_median_deg"] < 1.4
    assert f["height_out_of_range"] == 0


def test_plain_chain_baseline_surfaces(sim, tmp_path):
    assert _run(sim / "bundle", tmp_path / "f", "--surface", "fringe")["surface"] == "fringe"
    assert _run(sim / "bundle", tmp_path / "n", "--surface", "normals")["surface"] == "normals"


def test_plain_chain_bad_bundle_exits_2(sim, tmp_path, capsys):
    bundle = _subset(sim, tmp_path / "color", {"dark", "color"})
    out = tmp_path / "model"
    assert main([str(bundle), str(out), "--fusion", "plain", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "nothing to reconstruct" in err and "Traceback" not in err
    assert not out.exists()


# Pure functions -------------------------------------------------------------------------


def _hemisphere_normals(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = -np.abs(v[:, 2]) - 1.0  # facing the camera, slopes up to ~60°
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_least_squares_normals_drop_shadows_and_saturation():
    rng = np.random.default_rng(0)
    normals = _hemisphere_normals(rng, 400)
    albedo = rng.uniform(0.2, 0.8, 400)
    lights = light_directions(np.arange(8) * 45.0, 45.0)
    s = albedo[None] * np.maximum(0.0, lights @ normals.T)  # (K, P)
    s[0, :50] = 0.0  # cast shadows
    saturated = np.zeros_like(s, bool)
    s[1, 50:100] = 5.0  # clipped highlights, flagged
    saturated[1, 50:100] = True
    shading = s.reshape(8, 20, 20).astype(np.float32)
    n, rho, used = least_squares_normals(shading, lights, saturated=saturated.reshape(8, 20, 20))
    got = n.reshape(-1, 3)
    ok = used.ravel() >= 3
    assert ok.mean() > 0.95
    cos = np.sum(got[ok] * normals[ok], axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.05  # float32 shading
    np.testing.assert_allclose(rho.ravel()[ok], albedo[ok], rtol=1e-4)
    assert np.all(np.isnan(got[~ok]))


def test_least_squares_normals_needs_three_lit_samples():
    lights = light_directions([0.0, 90.0, 180.0, 270.0], 45.0)
    shading = np.zeros((4, 1, 1), np.float32)
    shading[:2] = 0.5  # two lit samples only
    n, rho, used = least_squares_normals(shading, lights)
    assert np.all(np.isnan(n)) and np.isnan(rho[0, 0]) and used[0, 0] == 2
    with pytest.raises(ValueError, match="light_dirs"):
        least_squares_normals(shading, lights[:3])


def test_average_azimuths_drops_a_wrong_order():
    h = np.full((4, 2, 3), 100.0, np.float32)
    h[:, 0, 0] = [100.0, 102.0, 98.0, 100.0 + 500.0]  # one azimuth a whole order off
    h[1:, 1, 2] = np.nan  # one azimuth only
    mean, n = average_azimuths_um(h, outlier_um=100.0, min_azimuths=2)
    assert mean[0, 0] == pytest.approx(100.0) and n[0, 0] == 3
    assert np.isnan(mean[1, 2]) and n[1, 2] == 0
    mean1, _ = average_azimuths_um(h, outlier_um=100.0)
    assert mean1[1, 2] == pytest.approx(100.0)


def test_fuse_plain_recovers_a_plane():
    rows, cols, s = 40, 50, 50.0
    r, c = np.mgrid[:rows, :cols].astype(np.float64)
    gx, gy = 0.3, -0.2
    plane = 20.0 + gx * c * s + gy * r * s
    n = np.stack([-gx * np.ones_like(r), -gy * np.ones_like(r), -np.ones_like(r)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = np.zeros((rows, cols), bool)
    mask[5:35, 5:45] = True
    rng = np.random.default_rng(1)
    fringe = (plane + rng.normal(0, 1.0, plane.shape)).astype(np.float32)
    fringe[15:20, 15:25] = np.nan  # a hole: slopes carry the surface across
    h = fuse_plain_um(n, fringe, mask, pixel_size_um=s)
    assert np.all(np.isnan(h[~mask])) and np.all(np.isfinite(h[mask]))
    assert np.abs(h - plane)[mask].max() < 1.0
    # Normals alone: the plane up to a constant (mean 0 over the mask).
    hn = fuse_plain_um(n, None, mask, pixel_size_um=s)
    err = (hn - plane)[mask]
    assert np.ptp(err) < 1e-2 and abs(hn[mask].mean()) < 1e-2
    # Fringe heights alone: the hole is filled by the membrane (a plane is harmonic).
    clean = plane.astype(np.float32).copy()
    clean[15:20, 15:25] = np.nan
    hf = fuse_plain_um(None, clean, mask, pixel_size_um=s)
    assert np.abs(hf - plane)[mask].max() < 0.5
    nf = normals_from_height(hf, pixel_size_um=s)
    assert np.all(np.isnan(nf[~mask])) and np.all(nf[mask][:, 2] < 0)
    with pytest.raises(ValueError, match="both be None"):
        fuse_plain_um(None, None, mask, pixel_size_um=s)


def test_fringe_weight_follows_the_pixel_size():
    assert fringe_weight(125.0) == pytest.approx(1.0)
    assert fringe_weight(62.5) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="pixel_size_um"):
        fringe_weight(0.0)


def test_plain_mask_keeps_the_bright_measured_part():
    r, c = np.mgrid[:60, :80]
    disk = (r - 30) ** 2 + (c - 40) ** 2 < 20**2
    brightness = np.where(disk, 0.4, 0.01).astype(np.float32)
    brightness[5, 5] = 0.5  # a bright speck on the support
    measured = np.ones_like(disk)
    measured[30, 40] = False  # a shadowed wedge floor inside is tablet all the same
    m = plain_mask(brightness, measured)
    assert not m[5, 5] and m[30, 40]
    inner = (r - 30) ** 2 + (c - 40) ** 2 < 18**2
    assert np.all(m[inner]) and not np.any(m[~disk])
