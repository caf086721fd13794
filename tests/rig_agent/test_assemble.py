"""A scan and its calibration make one valid bundle; mismatched calibrations are refused."""

from __future__ import annotations

import numpy as np
import pytest

from rig_agent.assemble import AssemblyError, build_manifest, write_scan_bundle
from rig_agent.patterns import ProjectorGeometry
from rig_agent.plan import Plan, expand, quick_plan
from rig_agent.spool import Spool
from worker.bundle import open_bundle, validate_bundle

H, W = 6, 8
GEOMETRY = ProjectorGeometry(width=32, height=24, pixel_size_um=100.0)
CAMERA = {"width": W, "height": H, "pixel_size_um": 50.0, "bit_depth": 12}


def spool_scan(spool, kind, plan, *, camera=CAMERA, seed=0):
    target = "reference" if kind == "calibration" else "object"
    meta = {
        "face": "reverse" if kind == "scan" else None,
        "tablet": {"designation": "P1"},
        "camera": camera,
        "polar_deg": 45.0,
        "reference_reflectance": 0.9,
    }
    scan = spool.create(kind=kind, shots=expand(plan, GEOMETRY, target=target), meta=meta)
    rng = np.random.default_rng(seed)
    for shot in scan.shots:
        scan.save_frame(shot, rng.integers(100, 4000, size=(H, W), dtype=np.uint16))
    return scan


def test_bundle_holds_object_and_reference_frames(tmp_path):
    spool = Spool(tmp_path)
    calibration = spool_scan(spool, "calibration", quick_plan())
    scan = spool_scan(spool, "scan", quick_plan(), seed=1)
    path = write_scan_bundle(scan, calibration)
    assert path == scan.path / "bundle.zip" and validate_bundle(path) == []
    assert scan.state["phase"] == "bundled"
    with open_bundle(path) as bundle:
        assert bundle.manifest.scan.face == "reverse"
        assert bundle.manifest.reference.reflectance == 0.9
        check = next(s for s in scan.shots if s.role == "check")
        assert check.file not in {f.file for f in bundle.frames}  # the check frame stays home
        shot = next(s for s in scan.shots if s.kind == "fringe")
        frame = next(f for f in bundle.frames if f.file == shot.file)
        np.testing.assert_array_equal(bundle.raw(frame), scan.load_frame(shot))
        assert bundle.reference_of(frame).file.startswith("reference/")


def test_a_calibration_with_another_plan_is_refused(tmp_path):
    spool = Spool(tmp_path)
    calibration = spool_scan(
        spool,
        "calibration",
        Plan(
            name="p", photometric_azimuths_deg=(0,), color_azimuths_deg=(), fringe_azimuths_deg=()
        ),
    )
    scan = spool_scan(spool, "scan", quick_plan())
    with pytest.raises(AssemblyError, match="rig-agent calibrate"):
        build_manifest(scan, calibration)


def test_a_calibration_with_another_camera_is_refused(tmp_path):
    spool = Spool(tmp_path)
    calibration = spool_scan(spool, "calibration", quick_plan(), camera=CAMERA | {"bit_depth": 10})
    scan = spool_scan(spool, "scan", quick_plan())
    with pytest.raises(AssemblyError, match="different camera"):
        build_manifest(scan, calibration)
