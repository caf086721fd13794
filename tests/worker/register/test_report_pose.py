"""The model directory's report carries scan.id, scan.face and scan.pose (registration needs them)."""

from __future__ import annotations

import json

import numpy as np

from worker.pipeline import reconstruct_bundle
from worker.simulate import simulate_scan
from worker.simulate.tablet import FACE_POSES


def test_report_carries_the_scan_pose(tmp_path):
    simulate_scan(tmp_path / "sim", seed=3, preset="quick", face="top", size=(48, 40))
    report = reconstruct_bundle(tmp_path / "sim" / "bundle", tmp_path / "model")
    on_disk = json.loads((tmp_path / "model" / "report.json").read_text())
    for r in (report, on_disk):
        assert r["scan"]["face"] == "top"
        assert r["scan"]["id"]
        assert np.allclose(r["scan"]["pose"], FACE_POSES["top"])
        assert r["pixel_size_um"] > 0
