"""The spool: one directory per scan, every frame on disk before the next move.

Layout of ``<spool root>/<scan id>/``::

    scan.json       what the scan is: kind (scan|calibration), tablet, face, plan, shots, devices
    journal.jsonl   one line per captured frame {key, file, sha256, captured_at}, fsync'ed
    frames/…        the frames as 8/16-bit PNG, named like the bundle will name them
    state.json      phase (capturing|interrupted|captured|bundled|uploaded), the last problem,
                    the upload id and confirmed ranges
    quality.json    the quality report;  bundle.zip  the bundle made from the frames

A frame is written atomically (temp, fsync, rename) and only then journaled; a frame
file that exists without its journal line (a crash between the two) is complete by
construction of the rename and is adopted on resume, so nothing is captured twice and
nothing is lost.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from rig_agent.fsutil import append_line_durable, atomic_write_json, read_json
from rig_agent.plan import Shot
from worker.durable import write_file_atomic

KINDS = ("scan", "calibration")


class SpoolError(RuntimeError):
    """The spool is missing, damaged or asked for something it does not hold."""


def utc_now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


def encode_png(image: np.ndarray) -> bytes:
    """Lossless single-channel PNG of a uint8 or uint16 frame (H, W)."""
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image must be (H, W) uint8 or uint16, got {image.shape} {image.dtype}")
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as img:
        array = np.asarray(img)
    return (
        array.astype(np.uint16) if array.dtype.kind in "iu" and array.dtype.itemsize > 1 else array
    )


@dataclass
class SpoolScan:
    """One scan's directory in the spool."""

    path: Path

    @property
    def id(self) -> str:
        return self.path.name

    @property
    def meta(self) -> dict[str, Any]:
        return read_json(self.path / "scan.json")

    @property
    def shots(self) -> list[Shot]:
        return [Shot.from_dict(d) for d in self.meta["shots"]]

    # -- state --------------------------------------------------------------------------
    @property
    def state(self) -> dict[str, Any]:
        return read_json(self.path / "state.json")

    def update_state(self, **changes: Any) -> dict[str, Any]:
        state = {**self.state, **changes, "updated_at": utc_now()}
        atomic_write_json(self.path / "state.json", state)
        return state

    # -- frames -------------------------------------------------------------------------
    def frame_path(self, shot: Shot) -> Path:
        return self.path / "frames" / shot.file

    def journal(self) -> dict[str, dict[str, Any]]:
        """Journal entries by shot key; a torn last line (power cut mid-write) is skipped."""
        entries: dict[str, dict[str, Any]] = {}
        path = self.path / "journal.jsonl"
        if not path.exists():
            return entries
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if isinstance(entry, dict) and "key" in entry:
                entries[entry["key"]] = entry
        return entries

    def recover(self) -> list[str]:
        """Adopt complete frame files the journal does not list yet; return their keys."""
        journal = self.journal()
        adopted = []
        for shot in self.shots:
            path = self.frame_path(shot)
            if shot.key in journal or not path.exists():
                continue
            data = path.read_bytes()
            try:
                decode_png(data)
            except Exception:  # unreadable: treat as never captured
                path.unlink()
                continue
            self._journal_append(shot, data)
            adopted.append(shot.key)
        return adopted

    def done_keys(self) -> set[str]:
        return {k for k, e in self.journal().items() if (self.path / "frames" / e["file"]).exists()}

    def pending(self) -> list[Shot]:
        done = self.done_keys()
        return [s for s in self.shots if s.key not in done]

    def save_frame(self, shot: Shot, image: np.ndarray) -> str:
        """Write the frame durably, then journal it; returns its sha256."""
        if shot.key in self.done_keys():
            raise SpoolError(f"frame {shot.file!r} of scan {self.id} is already captured")
        data = encode_png(image)
        write_file_atomic(self.frame_path(shot), data)
        return self._journal_append(shot, data)

    def _journal_append(self, shot: Shot, data: bytes) -> str:
        digest = hashlib.sha256(data).hexdigest()
        entry = {"key": shot.key, "file": shot.file, "sha256": digest, "captured_at": utc_now()}
        append_line_durable(self.path / "journal.jsonl", json.dumps(entry, sort_keys=True))
        return digest

    def load_frame(self, shot: Shot) -> np.ndarray:
        path = self.frame_path(shot)
        try:
            return decode_png(path.read_bytes())
        except FileNotFoundError as exc:
            raise SpoolError(f"frame {shot.file!r} is missing from scan {self.id}") from exc

    def verify(self) -> list[str]:
        """Files whose bytes no longer match their journal checksum."""
        bad = []
        for entry in self.journal().values():
            path = self.path / "frames" / entry["file"]
            if (
                not path.exists()
                or hashlib.sha256(path.read_bytes()).hexdigest() != entry["sha256"]
            ):
                bad.append(entry["file"])
        return bad


class Spool:
    """The spool root directory: create, open and list scans."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def create(self, *, kind: str, shots: list[Shot], meta: dict[str, Any]) -> SpoolScan:
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        scan_id = str(uuid.uuid4())
        final = self.root / scan_id
        tmp = self.root / f".{scan_id}.creating"
        (tmp / "frames").mkdir(parents=True)
        record = {
            **meta,
            "id": scan_id,
            "kind": kind,
            "created_at": utc_now(),
            "shots": [s.to_dict() for s in shots],
        }
        atomic_write_json(tmp / "scan.json", record)
        atomic_write_json(tmp / "state.json", {"phase": "capturing", "updated_at": utc_now()})
        tmp.rename(final)  # a scan directory is either complete or absent
        return SpoolScan(final)

    def open(self, scan_id: str) -> SpoolScan:
        matches = [s for s in self.scans() if s.id == scan_id or s.id.startswith(scan_id)]
        if not matches:
            raise SpoolError(f"no scan {scan_id!r} in the spool {str(self.root)!r}")
        if len(matches) > 1:
            raise SpoolError(f"{scan_id!r} matches several scans; give more of the id")
        return matches[0]

    def scans(self) -> list[SpoolScan]:
        if not self.root.exists():
            return []
        found = [SpoolScan(p) for p in self.root.iterdir() if (p / "scan.json").is_file()]
        return sorted(found, key=lambda s: (s.meta["created_at"], s.id))

    def latest_calibration(self) -> SpoolScan | None:
        done = [s for s in self.scans() if s.meta["kind"] == "calibration" and not s.pending()]
        return done[-1] if done else None

    def remove(self, scan: SpoolScan) -> None:
        shutil.rmtree(scan.path)
