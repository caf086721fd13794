"""Capture over the GRBL emulator's pseudo-terminal: every frame spooled, alarms resumable."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rig_agent.acquire import ScanInterrupted, capture
from rig_agent.devices.base import DeviceError
from rig_agent.devices.factory import Devices
from rig_agent.devices.grbl_emulator import GrblEmulator
from rig_agent.devices.projector import HeadlessProjector
from rig_agent.devices.simulated import SimulatedCamera
from rig_agent.devices.stage import GrblStage
from rig_agent.devices.transport import SerialLink
from rig_agent.patterns import ProjectorGeometry
from rig_agent.plan import expand, quick_plan
from rig_agent.spool import Spool

H, W = 12, 16
GEOMETRY = ProjectorGeometry(width=W, height=H, pixel_size_um=100.0)


def encode_light(*, pattern, azimuth_deg, target, exposure, rng):
    """A frame whose pixel (0, 0) records the azimuth the stage reported (tenths of a degree)
    and pixel (0, 1) the pattern kind, so tests can check what was lit when."""
    image = np.full((H, W), 100, dtype=np.uint16)
    image[0, 0] = round(azimuth_deg * 10)
    image[0, 1] = ("dark", "white", "color", "fringe").index(pattern.kind)
    return image


class FlakyCamera(SimulatedCamera):
    """Loses its USB connection once, on capture number ``fail_at``."""

    fail_at = 0

    def capture(self):
        if self.frames_taken + 1 == self.fail_at:
            self.fail_at = 0
            raise DeviceError("the camera returned no image; check its USB cable and power")
        return super().capture()


@pytest.fixture
def emulator():
    with GrblEmulator() as emu:
        yield emu


def open_rig(emulator, camera_class=SimulatedCamera) -> Devices:
    stage = GrblStage(SerialLink(emulator.port), poll_interval_s=0.002)
    stage.connect()
    projector = HeadlessProjector(GEOMETRY, render_images=False)
    camera = camera_class(
        stage=stage, projector=projector, renderer=encode_light, width=W, height=H, bit_depth=12
    )
    return Devices(stage=stage, camera=camera, projector=projector)


@pytest.fixture
def scan(tmp_path):
    shots = expand(quick_plan(), GEOMETRY, target="object")
    return Spool(tmp_path).create(kind="scan", shots=shots, meta={})


def journal_keys(scan) -> list[str]:
    lines = (scan.path / "journal.jsonl").read_text().splitlines()
    return [json.loads(line)["key"] for line in lines]


def test_every_frame_is_taken_at_its_azimuth_and_spooled(emulator, scan):
    devices = open_rig(emulator)
    seen = []
    try:
        capture(scan, devices, elevation_mm=2.0, progress=lambda d, t: seen.append((d, t)))
    finally:
        devices.close()
    shots = scan.shots
    assert scan.pending() == [] and scan.state["phase"] == "captured"
    assert sorted(journal_keys(scan)) == sorted(s.key for s in shots)
    for shot in shots:
        image = scan.load_frame(shot)
        if shot.kind != "dark":
            assert image[0, 0] == round(shot.azimuth_deg * 10), shot.file
        kind = {"dark": 0, "photometric": 1, "color": 2, "fringe": 3}[shot.kind]
        assert image[0, 1] == kind, shot.file
    assert seen[0] == (0, len(shots)) and seen[-1] == (len(shots), len(shots))
    # One move per azimuth: the plan groups shots by azimuth.
    moves = [line for line in emulator.received if line.startswith("G90")]
    assert len(moves) == len({s.azimuth_deg for s in shots if s.kind != "dark"}) + 1  # + check


def test_an_alarm_mid_scan_is_explained_and_the_scan_resumes(emulator, scan):
    emulator.hard_limit_on_move = 3
    devices = open_rig(emulator)
    with pytest.raises(ScanInterrupted) as info:
        capture(scan, devices, elevation_mm=0.0)
    devices.close()
    message = str(info.value)
    assert "hard limit switch was triggered" in message and "rig-agent resume" in message
    assert scan.id[:8] in message
    state = scan.state
    assert state["phase"] == "interrupted" and "ALARM:1" in state["problem"]
    captured_before = len(journal_keys(scan))
    assert 0 < captured_before < len(scan.shots)

    devices = open_rig(emulator)  # `rig-agent resume`: reconnect, re-home, continue
    try:
        assert devices.stage.needs_homing()
        capture(scan, devices, elevation_mm=0.0)
        taken_on_resume = devices.camera.frames_taken
    finally:
        devices.close()
    keys = journal_keys(scan)
    assert sorted(keys) == sorted(s.key for s in scan.shots)  # none lost, none twice
    assert taken_on_resume == len(scan.shots) - captured_before
    assert scan.state["phase"] == "captured" and scan.state["problem"] is None
    assert emulator.received.count("$H") == 2


def test_a_camera_failure_keeps_what_was_captured(emulator, scan):
    devices = open_rig(emulator, FlakyCamera)
    devices.camera.fail_at = 5
    with pytest.raises(ScanInterrupted, match="USB cable"):
        capture(scan, devices, elevation_mm=0.0)
    assert len(journal_keys(scan)) == 4
    capture(scan, devices, elevation_mm=0.0)  # same devices: no re-homing needed
    devices.close()
    assert sorted(journal_keys(scan)) == sorted(s.key for s in scan.shots)
    assert emulator.received.count("$H") == 1


def test_a_wrong_frame_size_stops_the_scan(emulator, scan):
    devices = open_rig(emulator)
    devices.camera.width = W + 1
    with pytest.raises(ScanInterrupted, match="instead of"):
        capture(scan, devices, elevation_mm=0.0)
    devices.close()
    assert not (scan.path / "journal.jsonl").exists()
