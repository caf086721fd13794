"""The spool keeps every frame durably and knows what is left to capture."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rig_agent.patterns import ProjectorGeometry
from rig_agent.plan import expand, quick_plan
from rig_agent.spool import Spool, SpoolError

GEOMETRY = ProjectorGeometry(width=64, height=48, pixel_size_um=100.0)


@pytest.fixture
def scan(tmp_path):
    shots = expand(quick_plan(), GEOMETRY, target="object")
    return Spool(tmp_path / "spool").create(kind="scan", shots=shots, meta={"face": "obverse"})


def frame(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 4096, size=(6, 8), dtype=np.uint16)


def test_frames_round_trip_losslessly_and_are_journaled(scan):
    shots = scan.shots
    digest = scan.save_frame(shots[0], frame(0))
    np.testing.assert_array_equal(scan.load_frame(shots[0]), frame(0))
    assert scan.journal()[shots[0].key]["sha256"] == digest
    assert [s.key for s in scan.pending()] == [s.key for s in shots[1:]]
    assert scan.verify() == []


def test_a_frame_is_never_captured_twice(scan):
    scan.save_frame(scan.shots[0], frame(0))
    with pytest.raises(SpoolError, match="already captured"):
        scan.save_frame(scan.shots[0], frame(1))
    np.testing.assert_array_equal(scan.load_frame(scan.shots[0]), frame(0))


def test_a_torn_journal_line_is_ignored(scan):
    scan.save_frame(scan.shots[0], frame(0))
    with open(scan.path / "journal.jsonl", "a") as handle:
        handle.write('{"key": "photometric_a9')  # power cut mid-line
    assert set(scan.journal()) == {scan.shots[0].key}


def test_a_renamed_frame_without_its_journal_line_is_adopted(scan):
    shots = scan.shots
    scan.save_frame(shots[0], frame(0))
    # Simulate a crash after the rename but before the journal append.
    scan.save_frame(shots[1], frame(1))
    lines = (scan.path / "journal.jsonl").read_text().splitlines()
    (scan.path / "journal.jsonl").write_text(lines[0] + "\n")
    assert shots[1] in scan.pending()
    assert scan.recover() == [shots[1].key]
    assert shots[1] not in scan.pending()


def test_no_temporary_files_are_left_behind(scan):
    for i, shot in enumerate(scan.shots[:3]):
        scan.save_frame(shot, frame(i))
    leftovers = [p for p in scan.path.rglob("*") if p.name.endswith(".tmp")]
    assert leftovers == []


def test_verify_reports_a_damaged_frame(scan):
    scan.save_frame(scan.shots[0], frame(0))
    scan.frame_path(scan.shots[0]).write_bytes(b"garbage")
    assert scan.verify() == [scan.shots[0].file]


def test_state_updates_are_merged(scan):
    scan.update_state(phase="interrupted", problem="ALARM:1")
    scan.update_state(phase="capturing")
    state = json.loads((scan.path / "state.json").read_text())
    assert state["phase"] == "capturing" and state["problem"] == "ALARM:1"


def test_open_by_prefix_list_and_latest_calibration(tmp_path):
    spool = Spool(tmp_path)
    shots = expand(quick_plan(), GEOMETRY, target="reference")[:2]
    cal = spool.create(kind="calibration", shots=shots, meta={})
    assert spool.latest_calibration() is None  # incomplete calibrations do not count
    for i, shot in enumerate(shots):
        cal.save_frame(shot, frame(i))
    assert spool.latest_calibration().id == cal.id
    assert spool.open(cal.id[:8]).id == cal.id
    with pytest.raises(SpoolError, match="no scan"):
        spool.open("nope")
    assert [s.id for s in spool.scans()] == [cal.id]


def test_bad_frames_are_refused(scan):
    with pytest.raises(ValueError, match="uint8 or uint16"):
        scan.save_frame(scan.shots[0], np.zeros((4, 4), dtype=np.float32))
    assert scan.pending() == scan.shots
