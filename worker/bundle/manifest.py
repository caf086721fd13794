"""``manifest.json`` of a scan bundle: strict JSON parsing, field rules, frozen dataclasses.

Implements the "manifest.json" tables of SCAN_BUNDLE.md v1. The cross-frame rules (fringe
sets, reference frames, unique files) live in `worker.bundle.matching`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from worker.bundle.errors import Problem
from worker.bundle.paths import normalize_path, path_problem

MANIFEST_NAME = "manifest.json"
FORMAT = "cuneiform-scan"
VERSION = 1
FACES = ("obverse", "reverse", "top", "bottom", "left", "right", "other")
KINDS = ("dark", "photometric", "color", "fringe")
TARGETS = ("object", "reference")
CHANNELS = ("red", "green", "blue")
MAX_MANIFEST_BYTES = 16 * 1024 * 1024


def is_simulated(tablet: Mapping[str, object] | None) -> bool:
    """Whether ``scan.tablet`` free metadata says the scan is simulated: ``"simulated":
    "true"`` (the convention of docs/simulator.md) or the simulator's own ``"simulator"`` key.
    Free metadata is not part of the contract; this is how this implementation reads it."""
    if not tablet:
        return False
    flag = str(tablet.get("simulated", "")).strip().lower()
    return flag in ("true", "1", "yes") or "simulator" in tablet


@dataclass(frozen=True)
class Scan:
    face: str
    id: str | None = None
    captured_at: str | None = None
    pose: tuple[tuple[float, float, float], ...] | None = None  # 3x3, row-major
    tablet: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    pixel_size_um: float
    bit_depth: int
    response_gamma: float = 1.0
    # σ of the calibrated Gaussian PSF on the object plane; None: nobody measured it.
    psf_sigma_px: float | None = None


@dataclass(frozen=True)
class Source:
    polar_deg: float


@dataclass(frozen=True)
class Reference:
    reflectance: float = 1.0


@dataclass(frozen=True)
class Frame:
    """One frame; ``index`` is its position in ``manifest["frames"]``, ``file`` is normalised.

    ``polar_deg`` is resolved (the frame's own or ``source.polar_deg``); it and
    ``azimuth_deg`` are None only for dark frames.
    """

    index: int
    file: str
    kind: str
    target: str = "object"
    azimuth_deg: float | None = None
    polar_deg: float | None = None
    channel: str | None = None
    period_um: float | None = None
    phase_deg: float | None = None
    exposure: float = 1.0


@dataclass(frozen=True)
class Manifest:
    format: str
    version: int
    scan: Scan
    camera: Camera
    source: Source
    reference: Reference
    frames: tuple[Frame, ...]


class _DuplicateKey(ValueError):
    pass


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not allowed in strict JSON")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text} overflows to infinity")
    return value


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(f"duplicate key {key!r}")
        out[key] = value
    return out


def parse_manifest_json(
    data: bytes, *, max_bytes: int = MAX_MANIFEST_BYTES
) -> tuple[Any, list[Problem]]:
    """Parse ``manifest.json`` bytes as strict RFC 8259 JSON in UTF-8.

    Returns ``(value, [])`` or ``(None, problems)``. Refuses NaN/Infinity, numbers that
    overflow, duplicate keys, invalid UTF-8, a byte-order mark and more than ``max_bytes``.
    """
    where = "manifest.json"
    if len(data) > max_bytes:
        return None, [Problem(where, f"is {len(data)} bytes, more than the cap of {max_bytes}")]
    if data.startswith(b"\xef\xbb\xbf"):
        return None, [Problem(where, "starts with a UTF-8 byte-order mark (not allowed)")]
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        return None, [Problem(where, f"is not valid UTF-8 ({exc.reason} at byte {exc.start})")]
    try:
        value = json.loads(
            text,
            object_pairs_hook=_unique_object,
            parse_constant=_reject_constant,
            parse_float=_finite_float,
        )
    except json.JSONDecodeError as exc:
        return None, [Problem(where, f"is not valid JSON: {exc.msg} (line {exc.lineno})")]
    except RecursionError:
        return None, [Problem(where, "is nested too deeply")]
    except ValueError as exc:  # duplicate keys, NaN, overflow, over-long integers
        return None, [Problem(where, f"is not strict JSON: {exc}")]
    if "\\u" in text and _has_lone_surrogate(value):
        return None, [Problem(where, "holds a \\u escape of a lone surrogate (not Unicode text)")]
    return value, []


def _has_lone_surrogate(value: Any) -> bool:
    """True if a string anywhere in ``value`` (keys included) cannot be encoded as UTF-8."""
    try:
        json.dumps(value, ensure_ascii=False).encode("utf-8")
    except UnicodeEncodeError:
        return True
    return False


def _is_number(value: Any) -> bool:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    if isinstance(value, int):
        return abs(value) < 2**1023  # beyond that float() overflows: not a finite number
    return not (isinstance(value, float) and not math.isfinite(value))


def _is_integral(value: Any) -> bool:
    return _is_number(value) and (isinstance(value, int) or value.is_integer())


class _Checker:
    """Collects problems while reading typed fields out of plain JSON values."""

    def __init__(self) -> None:
        self.problems: list[Problem] = []

    def add(self, where: str, message: str) -> None:
        self.problems.append(Problem(where, message))

    def obj(self, parent: dict, key: str, where: str, *, required: bool) -> dict | None:
        if key not in parent:
            if required:
                self.add(where, "required")
            return None
        value = parent[key]
        if not isinstance(value, dict):
            self.add(where, f"must be an object, not {_type_name(value)}")
            return None
        return value

    def number(
        self,
        parent: dict,
        key: str,
        where: str,
        *,
        required: bool | str,
        low: float | None = None,
        high: float | None = None,
        low_open: bool = True,
        high_open: bool = True,
        integer: bool = False,
    ) -> float | int | None:
        """``required`` may be a string: the reason it is required (e.g. a frame kind)."""
        if key not in parent:
            if required:
                self.add(where, "required" if required is True else f"required {required}")
            return None
        value = parent[key]
        kind = "an integer" if integer else "a number"
        if not _is_number(value) or (integer and not _is_integral(value)):
            self.add(where, f"must be {kind}, not {_describe(value)}")
            return None
        bad_low = low is not None and (value <= low if low_open else value < low)
        bad_high = high is not None and (value >= high if high_open else value > high)
        if bad_low or bad_high:
            self.add(
                where, f"{_describe(value)} is outside {_interval(low, high, low_open, high_open)}"
            )
            return None
        return int(value) if integer else float(value)

    def choice(
        self, parent: dict, key: str, where: str, options: tuple[str, ...], *, required: bool | str
    ) -> str | None:
        if key not in parent:
            if required:
                self.add(where, "required" if required is True else f"required {required}")
            return None
        value = parent[key]
        if not isinstance(value, str) or value not in options:
            listed = ", ".join(f'"{o}"' for o in options)
            self.add(where, f"{_describe(value)} is not one of {listed}")
            return None
        return value

    def string(self, parent: dict, key: str, where: str) -> str | None:
        if key not in parent:
            return None
        value = parent[key]
        if not isinstance(value, str):
            self.add(where, f"must be a string, not {_type_name(value)}")
            return None
        return value


def _type_name(value: Any) -> str:
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean"}
    if value is None:
        return "null"
    return names.get(type(value), "a number" if isinstance(value, int | float) else "a value")


def _describe(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return json.dumps(value)
    if isinstance(value, int) and abs(value) >= 10**40:
        return "a very large integer"  # repr of a huge int can even raise ValueError
    if isinstance(value, int | float | str):
        text = repr(value) if not isinstance(value, str) else json.dumps(value[:40])
        return text if len(text) <= 40 else text[:37] + "..."
    return _type_name(value)


def _interval(low, high, low_open, high_open) -> str:
    left = "(" if low_open else "["
    right = ")" if high_open else "]"
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    return f"{left}{lo}, {hi}{right}"


def check_manifest(value: Any) -> list[Problem]:
    """Every field-level problem of a parsed manifest (not the cross-frame rules)."""
    c = _Checker()
    if not isinstance(value, dict):
        c.add("manifest.json", f"must hold a JSON object, not {_type_name(value)}")
        return c.problems
    if value.get("format") != FORMAT:
        got = _describe(value["format"]) if "format" in value else "missing"
        c.add("format", f'must be "{FORMAT}" (got {got})')
    if "version" not in value:
        c.add("version", "required")
    elif not _is_integral(value["version"]) or value["version"] != VERSION:
        c.add("version", f"must be {VERSION} (got {_describe(value['version'])})")
    _check_scan(c, value)
    _check_camera(c, value)
    source = c.obj(value, "source", "source", required=True)
    if source is not None:
        c.number(source, "polar_deg", "source.polar_deg", required=True, low=0, high=90)
    reference = c.obj(value, "reference", "reference", required=False)
    if reference is not None:
        c.number(
            reference, "reflectance", "reference.reflectance", required=False,
            low=0, high=1, high_open=False,
        )  # fmt: skip
    if "frames" not in value:
        c.add("frames", "required")
    elif not isinstance(value["frames"], list):
        c.add("frames", f"must be a list, not {_type_name(value['frames'])}")
    else:
        for i, frame in enumerate(value["frames"]):
            _check_frame(c, frame, f"frames[{i}]")
    return c.problems


def _check_scan(c: _Checker, value: dict) -> None:
    scan = c.obj(value, "scan", "scan", required=True)
    if scan is None:
        if "scan" not in value:
            c.add("scan.face", "required")
        return
    c.string(scan, "id", "scan.id")
    captured = c.string(scan, "captured_at", "scan.captured_at")
    if captured is not None:
        try:
            datetime.fromisoformat(captured)
        except ValueError:
            c.add("scan.captured_at", f"{_describe(captured)} is not an ISO 8601 date-time")
    c.choice(scan, "face", "scan.face", FACES, required=True)
    if "pose" in scan:
        problem = _pose_problem(scan["pose"])
        if problem:
            c.add("scan.pose", problem)
    tablet = c.obj(scan, "tablet", "scan.tablet", required=False)
    for key, item in (tablet or {}).items():
        if not isinstance(item, str):
            shown = str(key) if len(str(key)) <= 40 else str(key)[:37] + "..."
            c.add(f"scan.tablet.{shown}", f"must be a string, not {_type_name(item)}")


def _pose_problem(pose: Any) -> str | None:
    rows_ok = isinstance(pose, list) and len(pose) == 3
    if not rows_ok or not all(isinstance(r, list) and len(r) == 3 for r in pose):
        return "must be a 3x3 matrix (a list of three lists of three numbers)"
    if not all(_is_number(x) and abs(x) <= 2 for r in pose for x in r):
        return "entries must be numbers in [-1, 1]"
    # A rotation: R Rᵀ = I and det R = +1; 1e-3 admits entries rounded to 4 decimals.
    for i in range(3):
        for j in range(3):
            dot = sum(pose[i][k] * pose[j][k] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                return "is not a rotation matrix (rows are not orthonormal)"
    (a, b, c_), (d, e, f), (g, h, i_) = pose
    det = a * (e * i_ - f * h) - b * (d * i_ - f * g) + c_ * (d * h - e * g)
    if det <= 0:
        return "is not a rotation matrix (determinant is not +1)"
    return None


def _check_camera(c: _Checker, value: dict) -> None:
    camera = c.obj(value, "camera", "camera", required=True)
    if camera is None:
        return
    for key in ("width", "height"):
        c.number(camera, key, f"camera.{key}", required=True, integer=True, low=1, low_open=False)
    c.number(camera, "pixel_size_um", "camera.pixel_size_um", required=True, low=0)
    c.number(
        camera, "bit_depth", "camera.bit_depth", required=True, integer=True,
        low=8, high=16, low_open=False, high_open=False,
    )  # fmt: skip
    c.number(camera, "response_gamma", "camera.response_gamma", required=False, low=0)
    c.number(camera, "psf_sigma_px", "camera.psf_sigma_px", required=False, low=0, low_open=False)


def _check_frame(c: _Checker, frame: Any, where: str) -> None:
    if not isinstance(frame, dict):
        c.add(where, f"must be an object, not {_type_name(frame)}")
        return
    if "file" not in frame:
        c.add(f"{where}.file", "required")
    else:
        problem = path_problem(frame["file"])
        if problem:
            c.add(f"{where}.file", problem)
    kind = c.choice(frame, "kind", f"{where}.kind", KINDS, required=True)
    c.choice(frame, "target", f"{where}.target", TARGETS, required=False)
    needs = f'for kind "{kind}"' if kind is not None else False
    c.number(frame, "azimuth_deg", f"{where}.azimuth_deg", required=kind != "dark" and needs)
    c.number(frame, "polar_deg", f"{where}.polar_deg", required=False, low=0, high=90)
    c.choice(frame, "channel", f"{where}.channel", CHANNELS, required=kind == "color" and needs)
    fringe = kind == "fringe" and needs
    c.number(frame, "period_um", f"{where}.period_um", required=fringe, low=0)
    c.number(frame, "phase_deg", f"{where}.phase_deg", required=fringe)
    c.number(frame, "exposure", f"{where}.exposure", required=False, low=0)


def _opt_float(value: Any) -> float | None:
    return None if value is None else float(value)


def build_manifest(value: dict) -> Manifest:
    """Typed `Manifest` with defaults applied; call only when `check_manifest` found nothing."""
    scan, cam = value["scan"], value["camera"]
    polar_deg = float(value["source"]["polar_deg"])
    pose = scan.get("pose")
    frames = []
    for i, f in enumerate(value["frames"]):
        dark = f["kind"] == "dark"
        frames.append(
            Frame(
                index=i,
                file=normalize_path(f["file"]),
                kind=f["kind"],
                target=f.get("target", "object"),
                azimuth_deg=_opt_float(f.get("azimuth_deg")),
                polar_deg=None if dark else float(f.get("polar_deg", polar_deg)),
                channel=f.get("channel"),
                period_um=_opt_float(f.get("period_um")),
                phase_deg=_opt_float(f.get("phase_deg")),
                exposure=float(f.get("exposure", 1.0)),
            )
        )
    return Manifest(
        format=value["format"],
        version=int(value["version"]),
        scan=Scan(
            face=scan["face"],
            id=scan.get("id"),
            captured_at=scan.get("captured_at"),
            pose=None if pose is None else tuple(tuple(float(x) for x in row) for row in pose),
            tablet=dict(scan.get("tablet", {})),
        ),
        camera=Camera(
            width=int(cam["width"]),
            height=int(cam["height"]),
            pixel_size_um=float(cam["pixel_size_um"]),
            bit_depth=int(cam["bit_depth"]),
            response_gamma=float(cam.get("response_gamma", 1.0)),
            psf_sigma_px=_opt_float(cam.get("psf_sigma_px")),
        ),
        source=Source(polar_deg=polar_deg),
        reference=Reference(reflectance=float(value.get("reference", {}).get("reflectance", 1.0))),
        frames=tuple(frames),
    )
