"""The CLI on the simulated rig: GRBL emulator on a pty, worker.simulate camera, real bundles."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rig_agent.__main__ import main
from rig_agent.devices.simulated import SimulatorScene
from rig_agent.spool import Spool, SpoolScan
from worker.bundle import open_bundle, validate_bundle
from worker.pipeline import reconstruct_bundle

TOKEN = "rig-test-token"  # the fake library's token (conftest)
PLAN = {
    "name": "tiny",
    "photometric_azimuths_deg": [0, 90, 180, 270],
    "color_azimuths_deg": [0],
    "fringe_azimuths_deg": [0, 90],
    "fringe_periods_across": [0.25, 1, 4],
}


@pytest.fixture
def config(tmp_path):
    (tmp_path / "plan.json").write_text(json.dumps(PLAN))
    path = tmp_path / "rig.toml"
    path.write_text(
        f'spool_dir = "{tmp_path / "spool"}"\n'
        'devices = "sim"\n'
        "camera_width = 64\ncamera_height = 48\npixel_size_um = 600.0\n"
        "projector_width = 96\nprojector_height = 72\nprojector_pixel_size_um = 400.0\n"
        f'plan = "{tmp_path / "plan.json"}"\n'
        "upload_backoff_s = 0.05\n"
    )
    return path


@pytest.mark.slow
def test_simulated_calibrate_scan_crash_resume_upload_clean(
    config, tmp_path, capsys, library, monkeypatch
):
    run = lambda *args: main(["--config", str(config), *args])  # noqa: E731

    assert run("scan", "--tablet", "P123456", "--face", "obverse") == 3
    assert "run `rig-agent calibrate` first" in capsys.readouterr().err

    assert run("calibrate") == 0

    # The scan PC "loses power" at the 10th frame: the process stops, the spool stays.
    real_save = SpoolScan.save_frame
    saved = []

    def save_then_crash(self, shot, image):
        if len(saved) == 9:
            raise KeyboardInterrupt
        saved.append(shot.key)
        return real_save(self, shot, image)

    monkeypatch.setattr(SpoolScan, "save_frame", save_then_crash)
    assert run("scan", "--tablet", "P123456", "--face", "obverse", "--museum-number", "BM 1") == 130
    assert "every frame captured so far is in the spool" in capsys.readouterr().err
    monkeypatch.setattr(SpoolScan, "save_frame", real_save)
    spool = Spool(tmp_path / "spool")
    calibration, scan = spool.scans()
    assert len(scan.pending()) == len(scan.shots) - 9
    assert scan.state["phase"] == "interrupted" and "KeyboardInterrupt" in scan.state["problem"]

    assert run("resume") == 0
    out = capsys.readouterr().out
    assert "Quality check passed" in out and "ready to upload" in out
    keys = [
        json.loads(line)["key"] for line in (scan.path / "journal.jsonl").read_text().splitlines()
    ]
    assert sorted(keys) == sorted(s.key for s in scan.shots)  # none twice, none lost
    bundle = scan.path / "bundle.zip"
    assert validate_bundle(bundle) == []
    with open_bundle(bundle) as opened:
        manifest = opened.manifest
        frames = opened.frames
        assert manifest.scan.id == scan.id and manifest.scan.face == "obverse"
        assert manifest.scan.tablet == {"designation": "P123456", "museum_number": "BM 1"}
        assert manifest.camera.width == 64 and manifest.camera.bit_depth == 12
        assert manifest.source.polar_deg == 45.0
        for frame in frames:
            if frame.target == "object" and frame.kind != "dark":
                assert opened.reference_of(frame) is not None, frame.file
    objects = [f for f in frames if f.target == "object"]
    assert len(objects) == len([s for s in scan.shots if s.role == "bundle"])
    assert len(frames) - len(objects) == len(calibration.shots)

    # The bundle reconstructs, close to the simulator's ground truth.
    report = reconstruct_bundle(bundle, tmp_path / "model")
    assert report["quality"]["coverage"] > 0.9
    truth = SimulatorScene(width=64, height=48, pixel_size_um=600.0, polar_deg=45.0)
    truth = truth.view("object").ground_truth()
    height_um = np.load(tmp_path / "model" / "height.npy")
    both = truth["mask"] & np.isfinite(height_um)
    assert both.sum() > 0.8 * truth["mask"].sum()
    # Fringe phase noise σ_φ ≈ 0.01 rad on the finest period P = 7.2 mm gives
    # σ_h = σ_φ·P/(2π·tan θ) ≈ 11 µm; the limit (a sixth of a 600 µm pixel) leaves room for
    # the camera blur across wedge edges, which the phase cannot resolve.
    error_um = np.median(np.abs(height_um[both] - truth["height"][both]))
    assert error_um < 100.0

    assert run("status") == 0
    status = capsys.readouterr().out
    assert scan.id[:8] in status and "bundled" in status and calibration.id[:8] in status

    # The operator must force an upload that failed its quality check.
    quality = json.loads((scan.path / "quality.json").read_text())
    (scan.path / "quality.json").write_text(json.dumps(quality | {"ok": False}))
    monkeypatch.setenv("RIG_AGENT_LIBRARY_URL", library.url)
    monkeypatch.setenv("RIG_AGENT_API_TOKEN", TOKEN)
    assert run("upload", scan.id[:8]) == 1
    assert "--force" in capsys.readouterr().err
    assert run("upload", "--force", scan.id[:8]) == 0
    assert "reconstruction job 1" in capsys.readouterr().out
    assert library.stored_sha256() == scan.state["upload"]["confirmed_sha256"]

    assert run("clean") == 0
    assert [s.id for s in spool.scans()] == [calibration.id]  # calibrations are kept


def test_resume_with_nothing_to_do_and_bad_arguments(config, capsys):
    assert main(["--config", str(config), "resume"]) == 0
    assert "nothing to resume" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        main(["--config", str(config), "scan", "--tablet", "P1", "--face", "front"])
    assert info.value.code == 2
    assert main(["--config", str(config), "check", "deadbeef"]) == 3
    assert "no scan 'deadbeef'" in capsys.readouterr().err


def test_a_bad_plan_file_is_named(config, tmp_path, capsys):
    (tmp_path / "plan.json").write_text('{"fringe_phases_deg": [0, 120, 240]}')
    assert main(["--config", str(config), "calibrate"]) == 2
    err = capsys.readouterr().err
    assert "plan.json" in err and "fringe_phases_deg" in err and "Traceback" not in err


def test_projector_screen_option_overrides_the_setting(config, capsys):
    assert main(["--config", str(config), "--projector-screen", "3", "status"]) == 0
    assert main(["--config", str(config), "--projector-screen", "-1", "status"]) == 2
    err = capsys.readouterr().err
    assert "projector_screen" in err and "Traceback" not in err
