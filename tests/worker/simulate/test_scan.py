"""End to end: simulate a (tiny) scan, validate and read the bundle, check the ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from worker.bundle import open_bundle, validate_bundle
from worker.simulate.__main__ import main
from worker.simulate.acquisition import PRESETS, pixel_size_for, plan_frames
from worker.simulate.noise import noise_model
from worker.simulate.rig import FrameSpec, frame_radiance, render_frame
from worker.simulate.scan import scan_rig, scene, simulate_scan
from worker.simulate.tablet import FACE_POSES, make_tablet

SIZE = (64, 48)  # the quick preset's field at 536 µm pixels: tiny but complete


@pytest.fixture(scope="module")
def hard_scan(tmp_path_factory):
    out = tmp_path_factory.mktemp("hard")
    return simulate_scan(out, seed=4, size=SIZE, noise="hard")


def test_bundle_validates_and_holds_the_standard_acquisition(hard_scan):
    bundle = hard_scan.bundles["obverse"]
    assert validate_bundle(bundle) == []
    with open_bundle(bundle) as b:
        kinds = [f.kind for f in b.frames]
        assert kinds.count("photometric") == 2 * 8
        assert kinds.count("color") == 2 * 4 * 3
        assert kinds.count("fringe") == 2 * 4 * 10 * 4
        assert kinds.count("dark") == len({f.exposure for f in b.frames}) == 3  # hard: 3 exposures
        for f in b.frames:
            if f.kind != "dark" and f.target == "object":
                assert b.reference_of(f) is not None
        assert b.manifest.camera.pixel_size_um == pytest.approx(pixel_size_for(*SIZE))


def test_read_back_radiance_matches_the_model_within_noise(hard_scan):
    """The reader's (lin(v) - lin(v_dark)) / exposure recovers the simulated radiance."""
    noise = noise_model("hard")
    view = hard_scan.views["obverse"]
    rig = scan_rig(4, *SIZE, view.pixel_size_um, noise)
    with open_bundle(hard_scan.bundles["obverse"]) as b:
        for f in b.frames_where(kind="photometric", target="object")[:4]:
            spec = FrameSpec(
                "photometric", "object", f.azimuth_deg, f.polar_deg, exposure=f.exposure
            )
            truth = frame_radiance(view, spec, rig, noise)
            read = b.radiance(f)
            ok = truth * f.exposure < 0.9  # not saturated
            sigma = np.array([noise.radiance_sigma(t, f.exposure) for t in truth[ok]])
            z = (read[ok] - truth[ok]) / sigma
            # Per-pixel errors are ~N(0, 1) by construction of radiance_sigma: |z| < 6 everywhere
            # (48·64 pixels: P(|z| > 6) ~ 1e-9 each) and the mean within 6/sqrt(n).
            assert np.max(np.abs(z)) < 6
            assert abs(z.mean()) < 6 / np.sqrt(z.size)


def test_ground_truth_is_written_beside_the_bundle(hard_scan):
    gt = hard_scan.gt_dirs["obverse"]
    assert gt.parent == hard_scan.bundles["obverse"].parent
    h, n = np.load(gt / "height.npy"), np.load(gt / "normals.npy")
    albedo, mask = np.load(gt / "albedo.npy"), np.load(gt / "mask.npy")
    assert h.shape == mask.shape == SIZE[::-1] and n.shape == albedo.shape == (*SIZE[::-1], 3)
    assert mask.dtype == bool and 0.3 < mask.mean() < 0.9
    assert np.isfinite(h[mask]).all() and np.isnan(h[~mask]).all()
    assert np.allclose(np.linalg.norm(n[mask], axis=-1), 1, atol=1e-5) and (n[mask][:, 2] < 0).all()
    wedges = json.loads((gt / "wedges.json").read_text())["wedges"]
    assert len(wedges) > 10
    for w in wedges:
        assert 0 <= w["bottom"]["row"] <= SIZE[1] - 1 and 0 <= w["bottom"]["col"] <= SIZE[0] - 1
        # Face-on (tilt < 60°) the rim lies above the bottom by depth·cos(tilt), plus at most
        # 0.033·width·sin(tilt) because the rim's centroid is 0.033·width ahead of the apex.
        assert 0.5 * w["depth_um"] < w["depth_view_um"] <= w["depth_um"] + 0.034 * w["width_um"]


def test_same_seed_same_bytes(tmp_path):
    a = simulate_scan(tmp_path / "a", seed=9, size=(32, 24), noise="default", as_zip=True)
    b = simulate_scan(tmp_path / "b", seed=9, size=(32, 24), noise="default", as_zip=True)
    assert a.bundles["obverse"].read_bytes() == b.bundles["obverse"].read_bytes()
    for name in ("height.npy", "normals.npy", "albedo.npy", "mask.npy", "wedges.json"):
        assert (a.gt_dirs["obverse"] / name).read_bytes() == (
            b.gt_dirs["obverse"] / name
        ).read_bytes()
    assert validate_bundle(a.bundles["obverse"]) == []


def test_paper_preset_plans_the_papers_acquisition():
    preset = PRESETS["paper"]
    pixel = pixel_size_for(preset.width, preset.height)
    assert (preset.width, preset.height, pixel) == (1280, 1024, pytest.approx(26.8))
    frames = plan_frames(
        preset,
        width=1280,
        height=1024,
        pixel_size_um=pixel,
        noise=noise_model("default"),
        rng=np.random.default_rng(0),
    )
    assert 350 <= len(frames) <= 450
    fringe = [
        f for f in frames if f.kind == "fringe" and f.target == "object" and f.azimuth_deg == 0
    ]
    periods = sorted({f.period_um for f in fringe})
    # φ = 0: u = +y, the field's extent along u is 1024·26.8 µm; 128 … 0.25 periods across.
    assert periods[0] == pytest.approx(1024 * 26.8 / 128)
    assert periods[-1] == pytest.approx(1024 * 26.8 / 0.25)
    assert np.allclose(np.diff(np.log2(periods)), 1)


def test_cli_rejects_bad_arguments_with_exit_2(tmp_path, capsys):
    for argv in (
        ["--size", "12x5"],
        ["--size", "big"],
        ["--face", "sideways"],
        ["--preset", "huge"],
        ["--noise", "loud"],
        ["--seed", "-1"],
    ):
        with pytest.raises(SystemExit) as exc:
            main(["--out", str(tmp_path / "x"), *argv])
        assert exc.value.code == 2
        assert "Traceback" not in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_cli_refuses_to_overwrite(tmp_path, capsys):
    (tmp_path / "bundle").mkdir()
    assert main(["--out", str(tmp_path), "--size", "32x24"]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle"]


def test_clean_bundle_reconstructs_with_textbook_methods(tmp_path):
    """Temporal phase unwrapping and Lambertian photometric stereo recover the ground truth."""
    result = simulate_scan(tmp_path, seed=5, size=(96, 80), noise="clean")
    gt = result.gt_dirs["obverse"]
    gt_h, mask = np.load(gt / "height.npy"), np.load(gt / "mask.npy")
    # Photometric stereo measures a pixel's mean normal; gt/normals.npy is the normal at the
    # pixel centre (SCAN_BUNDLE.md's output), which carries roughness finer than the pixel.
    gt_n = result.views["obverse"].ground_truth()["normals"]
    with open_bundle(result.bundles["obverse"]) as b:
        s_um = b.manifest.camera.pixel_size_um

        def wrapped_phase(target: str, period: float) -> np.ndarray:
            i = {
                f.phase_deg: b.radiance(f)
                for f in b.frames_where(kind="fringe", target=target, azimuth_deg=90.0)
                if abs(f.period_um - period) < 1e-6
            }
            return np.arctan2(i[270.0] - i[90.0], i[0.0] - i[180.0])

        periods = sorted({f.period_um for f in b.frames_where(kind="fringe", azimuth_deg=90.0)})
        h = None
        for period in reversed(periods):  # coarsest first: unambiguous, then refine
            if period < 8 * s_um:
                break
            d = np.angle(
                np.exp(1j * (wrapped_phase("object", period) - wrapped_phase("reference", period)))
            )
            k = 2 * np.pi * np.tan(np.radians(45.0)) / period  # Δψ = -k·h
            if h is not None:
                d += 2 * np.pi * np.round((-k * h - d) / (2 * np.pi))
            h = -d / k
        lights, ratios = [], []
        for f in b.frames_where(kind="photometric", target="object"):
            th, ph = np.radians(f.polar_deg), np.radians(f.azimuth_deg)
            lights.append([np.sin(th) * np.sin(ph), np.sin(th) * np.cos(ph), -np.cos(th)])
            ratios.append(b.radiance(f) / b.radiance(b.reference_of(f)) * 0.95 * np.cos(th))
    # Clean: quantisation alone moves heights by ~0.02 µm. What remains is the pixel box: the
    # phase of a box-averaged fringe is that of the centre height for a planar patch, off by
    # the in-pixel sag κ·s²/8 <= 357²/(8·3800) ≈ 4.2 µm on the pillow (edge radius >= 3.8 mm).
    # Shadows and crease pixels break the model (no masking here), so test the median.
    assert np.median(np.abs(h - gt_h)[mask]) < 5.0
    g = np.stack(ratios, -1)[mask] @ np.linalg.pinv(np.array(lights)).T
    n = g / np.linalg.norm(g, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(n * gt_n[mask], axis=1), -1, 1)))
    # Unshadowed Lambertian pixels give the mean unit normal, gt the mean slope: they differ by
    # O(slope variance in the pixel) ≈ (0.025 roughness slope)² rad, far below 0.5°.
    assert np.median(angle) < 0.5


def test_all_faces_poses_and_mesh_agree(tmp_path):
    result = simulate_scan(tmp_path, seed=2, size=(32, 24), face="all", noise="clean", as_zip=True)
    poses = json.loads((tmp_path / "poses.json").read_text())["poses"]
    mesh = trimesh.load(tmp_path / "tablet.ply", force="mesh")
    assert mesh.is_watertight
    verts_um = np.asarray(mesh.vertices) * 1000.0
    for face, bundle in result.bundles.items():
        with open_bundle(bundle) as b:
            assert b.manifest.scan.face == face
            assert np.allclose(b.manifest.scan.pose, poses[face]["rotation"])
        view_pts = verts_um @ np.array(poses[face]["rotation"]).T + poses[face]["translation_um"]
        gt_h = np.load(result.gt_dirs[face] / "height.npy")
        # The highest mesh vertex is the top of the face, where the surface is flat: it matches
        # the highest pixel mean up to the roughness inside one 1 mm pixel (< 10 µm) and the
        # mesh's vertex spacing sag (< 1 µm); 60 µm leaves room for the low-frequency waves.
        assert (-view_pts[:, 2]).max() == pytest.approx(np.nanmax(gt_h), abs=60.0)


def test_oblique_pose_is_recorded(tmp_path):
    tilt = np.radians(20.0)
    pose = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    result = simulate_scan(tmp_path, seed=2, size=(32, 24), face="other", pose=pose, as_zip=True)
    with open_bundle(result.bundles["other"]) as b:
        assert b.manifest.scan.face == "other"
        assert np.allclose(b.manifest.scan.pose, pose)
    with pytest.raises(ValueError, match="pose"):
        simulate_scan(tmp_path / "x", face="obverse", pose=np.ones((3, 3)))


def test_simulated_camera_path_reproduces_the_bundle_frames(hard_scan):
    """scene() + render_frame (the rig agent's camera) give the bundle's exact values."""
    noise = noise_model("hard")
    view, rig = scene(make_tablet(4), FACE_POSES["obverse"], seed=4, size=SIZE, noise=noise)
    with open_bundle(hard_scan.bundles["obverse"]) as b:
        for f in (
            b.frames[0],
            *b.frames_where(kind="fringe", target="object")[:2],
            *b.frames_where(kind="color", target="reference")[:1],
        ):
            spec = FrameSpec(
                f.kind,
                f.target,
                f.azimuth_deg,
                f.polar_deg or 45.0,
                f.channel,
                f.period_um,
                f.phase_deg,
                f.exposure,
            )
            rng = np.random.default_rng([4, 0, f.index])  # seed, face, frame index
            assert np.array_equal(render_frame(view, spec, noise, rng, rig=rig), b.raw(f))
