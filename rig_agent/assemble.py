"""Make a bundle (SCAN_BUNDLE.md) from a scan's frames and its calibration's frames.

The manifest names the object frames of the scan and the reference frames of the
calibration; every object light must have its reference light (same kind, azimuth,
channel, period and phase), so a calibration made with another plan or another
projector is refused with a message that says to calibrate again.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rig_agent.plan import Shot
from rig_agent.spool import SpoolScan


class AssemblyError(RuntimeError):
    """The scan and its calibration cannot make a valid bundle."""


def build_manifest(scan: SpoolScan, calibration: SpoolScan) -> dict[str, Any]:
    """The manifest.json content for ``scan`` with the reference frames of ``calibration``."""
    meta, cal = scan.meta, calibration.meta
    for key in ("camera", "polar_deg"):
        if meta[key] != cal[key]:
            raise AssemblyError(
                f"the calibration {calibration.id[:8]} was made with a different {key} "
                f"({cal[key]!r}, this scan {meta[key]!r}); run `rig-agent calibrate` again"
            )
    objects = [s for s in scan.shots if s.role == "bundle"]
    references = {s.light_key(): s for s in calibration.shots}
    missing = [s.file for s in objects if s.kind != "dark" and s.light_key() not in references]
    if missing:
        raise AssemblyError(
            f"the calibration {calibration.id[:8]} has no reference frame for {len(missing)} "
            f"frames of this scan (e.g. {missing[0]}): it was made with another plan or "
            "projector; run `rig-agent calibrate` with the current plan"
        )
    scan_info: dict[str, Any] = {
        "id": meta["id"],
        "captured_at": meta["created_at"],
        "face": meta["face"],
    }
    if meta.get("tablet"):
        scan_info["tablet"] = meta["tablet"]
    return {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": scan_info,
        "camera": meta["camera"],
        "source": {"polar_deg": meta["polar_deg"]},
        "reference": {"reflectance": meta["reference_reflectance"]},
        "frames": [s.manifest_frame() for s in objects]
        + [s.manifest_frame() for s in calibration.shots],
    }


class SpooledFrames(Mapping[str, np.ndarray]):
    """Frames by bundle path, decoded from the spool only when asked for: a standard scan
    and its calibration hold hundreds of megapixel frames, more than should sit in memory."""

    def __init__(self, sources: dict[str, tuple[SpoolScan, Shot]]) -> None:
        self._sources = sources

    def __getitem__(self, file: str) -> np.ndarray:
        scan, shot = self._sources[file]
        return scan.load_frame(shot)

    def __iter__(self) -> Iterator[str]:
        return iter(self._sources)

    def __len__(self) -> int:
        return len(self._sources)


def write_scan_bundle(scan: SpoolScan, calibration: SpoolScan, out: Path | None = None) -> Path:
    """Write ``bundle.zip`` into the scan's spool directory (validated, atomic)."""
    from worker.bundle import BundleError, write_bundle

    manifest = build_manifest(scan, calibration)
    sources = {s.file: (scan, s) for s in scan.shots if s.role == "bundle"}
    sources.update({s.file: (calibration, s) for s in calibration.shots})
    images = SpooledFrames(sources)
    out = out or scan.path / "bundle.zip"
    try:
        write_bundle(out, manifest, images, as_zip=True, overwrite=True)
    except BundleError as exc:
        raise AssemblyError(f"the bundle of scan {scan.id[:8]} is not valid: {exc}") from exc
    scan.update_state(phase="bundled", bundle=out.name)
    return out
