"""The operator's workflows, between the CLI and the parts: calibrate, scan, resume, check.

Each function takes the settings and the spool explicitly; the CLI only parses
arguments, shows progress and turns errors into messages.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from rig_agent.acquire import capture
from rig_agent.assemble import AssemblyError, write_scan_bundle
from rig_agent.devices.factory import open_devices, projector_geometry
from rig_agent.fsutil import atomic_write_json
from rig_agent.plan import Plan, expand, load_plan, quick_plan
from rig_agent.quality import QualityReport, check_scan
from rig_agent.settings import Settings
from rig_agent.spool import Spool, SpoolError, SpoolScan

FACES = ("obverse", "reverse", "top", "bottom", "left", "right", "other")
Progress = Callable[[int, int], None]


def resolve_plan(name: str) -> Plan:
    """``standard``, ``quick`` or the path of a plan file."""
    if name == "standard":
        return Plan()
    if name == "quick":
        return quick_plan()
    return load_plan(name)


def camera_record(settings: Settings, bit_depth: int) -> dict[str, Any]:
    return {
        "width": settings.camera_width,
        "height": settings.camera_height,
        "pixel_size_um": settings.pixel_size_um,
        "bit_depth": bit_depth,
    }


def start(
    settings: Settings,
    spool: Spool,
    *,
    kind: str,
    face: str | None = None,
    tablet: dict[str, str] | None = None,
) -> SpoolScan:
    """Create the spool entry of a new calibration or scan (nothing is captured yet)."""
    plan = resolve_plan(settings.plan)
    calibration = None
    if kind == "scan":
        if face not in FACES:
            raise ValueError(f"face must be one of {', '.join(FACES)}, got {face!r}")
        calibration = spool.latest_calibration()
        if calibration is None:
            raise SpoolError(
                "there is no complete calibration yet: run `rig-agent calibrate` first"
            )
    target = "reference" if kind == "calibration" else "object"
    shots = expand(plan, projector_geometry(settings), target=target)
    meta = {
        "face": face,
        "tablet": tablet or {},
        "plan": plan.to_dict(),
        "projector": dataclasses.asdict(projector_geometry(settings)),
        "polar_deg": settings.polar_deg,
        "elevation_mm": settings.elevation_mm,
        "averaging": plan.averaging,
        "calibration_id": calibration.id if calibration else None,
        "devices": settings.devices,
    }
    return spool.create(kind=kind, shots=shots, meta=meta)


def run_capture(scan: SpoolScan, settings: Settings, *, progress: Progress | None = None) -> None:
    """Open the devices, capture the scan's pending shots, close the devices."""
    meta = scan.meta
    target = "reference" if meta["kind"] == "calibration" else "object"
    devices = open_devices(settings, target=target, face=meta.get("face"))
    try:
        record = camera_record(settings, devices.camera.bit_depth)
        reflectance = devices.reference_reflectance or settings.reference_reflectance
        _remember_devices(scan, camera=record, reference_reflectance=reflectance)
        capture(
            scan,
            devices,
            elevation_mm=meta["elevation_mm"],
            averaging=meta["averaging"],
            progress=progress,
        )
    finally:
        devices.close()


def _remember_devices(scan: SpoolScan, **values: Any) -> None:
    """Record the camera on first capture; refuse to resume with a different camera."""
    meta = scan.meta
    for key, value in values.items():
        if key in meta and meta[key] != value:
            raise SpoolError(
                f"scan {scan.id[:8]} was started with {key} {meta[key]!r} but the rig now has "
                f"{value!r}; restore the settings to resume it"
            )
    if any(key not in meta for key in values):
        atomic_write_json(scan.path / "scan.json", {**meta, **values})


def check(scan: SpoolScan) -> QualityReport:
    """Run the quality checks and store ``quality.json``."""
    meta = scan.meta
    report = check_scan(
        scan.shots,
        scan.load_frame,
        captured=scan.done_keys(),
        bit_depth=meta["camera"]["bit_depth"],
    )
    atomic_write_json(scan.path / "quality.json", report.to_dict())
    return report


def finish(scan: SpoolScan, spool: Spool) -> QualityReport:
    """Quality check, then (for a complete object scan) the bundle with its calibration."""
    report = check(scan)
    meta = scan.meta
    already = scan.state.get("phase") in ("bundled", "uploaded")
    if already and (scan.path / "bundle.zip").is_file():
        return report  # never rewrite a bundle that may be (partly) uploaded
    if meta["kind"] == "scan" and not scan.pending():
        calibration = spool.open(meta["calibration_id"])
        if calibration.pending():
            raise AssemblyError(f"the calibration {calibration.id[:8]} is incomplete")
        write_scan_bundle(scan, calibration)
    elif meta["kind"] == "calibration" and not scan.pending():
        scan.update_state(phase="captured")
    return report
