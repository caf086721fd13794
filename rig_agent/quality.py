"""Quality checks on a captured scan, before it leaves the scanner.

Each check works on the stored frame values (H, W) of one scan and produces
findings an operator can act on: which frames, what is wrong, what to do. Errors
block the upload (``--force`` overrides); warnings are reported only.

Checks (all fractions relative to full scale F = 2^bit_depth − 1):

* missing frames — shots of the plan with no frame in the spool;
* saturation — more than ``saturated_fraction`` of the pixels at F;
* under-exposure — the 99th percentile of (frame − dark) below ``dark_level`` · F;
* fringe modulation — for a set of four phase steps I₀, I₉₀, I₁₈₀, I₂₇₀ the mean is
  A = ΣI/4 and the amplitude B = ½·√((I₀ − I₁₈₀)² + (I₉₀ − I₂₇₀)²); the median of B/A on
  lit pixels below ``min_modulation``;
* fringe drift — I₀ + I₁₈₀ = I₉₀ + I₂₇₀ = 2A for a still tablet, so the RMS of their
  difference, relative to 2·mean(A), above ``max_drift``;
* moved tablet — the check frame (the first photometric light repeated at the end) fitted
  to the first one by a scale s (light drift), relative RMS of check − s·first above
  ``max_moved``.

Both comparisons are made on sums over b×b tiles (b = ``bin_px``) of fully lit pixels:
white noise of σ per pixel gives a relative RMS of about √2·σ/(b·mean) for the moved
check and 2σ/(b·2·mean A) for the drift — with b = 4, under 1 % when the mean signal
exceeds ~35σ — while a tablet shifted by a pixel or more changes the tiles along every
edge, wedge and its outline. Average frames (plan ``averaging``) if a camera is noisier.

Frames are read when a check needs them (a standard scan does not fit in memory as
float arrays), each at most twice.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field

import numpy as np

from rig_agent.plan import Shot


@dataclass(frozen=True)
class Thresholds:
    """Limits of the checks (fractions; see the module docstring)."""

    saturated_fraction: float = 0.005
    dark_level: float = 0.05
    min_modulation: float = 0.08
    max_drift: float = 0.03
    max_moved: float = 0.03
    lit_fraction: float = 0.02  # pixels brighter than this · F count as lit
    bin_px: int = 4  # block size for the moved/drift comparisons


def bin_sum(image: np.ndarray, block: int) -> np.ndarray:
    """Sums over ``block``×``block`` tiles (edges that do not fill a tile are dropped)."""
    h, w = (image.shape[0] // block) * block, (image.shape[1] // block) * block
    return image[:h, :w].reshape(h // block, block, w // block, block).sum(axis=(1, 3))


def _relative_rms(a: np.ndarray, b: np.ndarray, lit: np.ndarray, block: int) -> float:
    """RMS of (b − a) over fully lit tiles, relative to the mean of a there.

    Comparing tile sums divides white noise by ``block`` while a shifted tablet (edges,
    wedges, its outline) still differs tile by tile.
    """
    tiles_lit = bin_sum(lit.astype(np.int64), block) == block * block
    if not tiles_lit.any():
        return 0.0
    a_t, b_t = bin_sum(a, block)[tiles_lit], bin_sum(b, block)[tiles_lit]
    return float(np.sqrt(np.mean((b_t - a_t) ** 2)) / np.mean(a_t))


@dataclass(frozen=True)
class Finding:
    level: str  # "error" or "warning"
    check: str
    frames: tuple[str, ...]
    message: str
    advice: str


@dataclass
class QualityReport:
    findings: list[Finding] = field(default_factory=list)
    figures: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not any(f.level == "error" for f in self.findings)

    def to_dict(self) -> dict:
        return {
            "ok": self.ok,
            "findings": [asdict(f) | {"frames": list(f.frames)} for f in self.findings],
            "figures": self.figures,
        }

    def to_text(self) -> str:
        if not self.findings:
            return "Quality check passed: every frame is present, exposed and steady."
        lines = ["Quality check FAILED:" if not self.ok else "Quality check passed with warnings:"]
        for f in self.findings:
            shown = ", ".join(f.frames[:4]) + (
                f" and {len(f.frames) - 4} more" if len(f.frames) > 4 else ""
            )
            lines.append(f"- [{f.level}] {f.message}")
            if shown:
                lines.append(f"    frames: {shown}")
            lines.append(f"    what to do: {f.advice}")
        return "\n".join(lines)


Loader = Callable[[Shot], np.ndarray]


def check_scan(
    shots: Iterable[Shot],
    load: Loader,
    *,
    captured: set[str],
    bit_depth: int,
    thresholds: Thresholds | None = None,
) -> QualityReport:
    """Run every check on the captured frames of one target; ``load`` reads a shot's frame."""
    if not 1 <= bit_depth <= 16:
        raise ValueError(f"bit_depth must be in 1..16, got {bit_depth!r}")
    limits = thresholds or Thresholds()
    full = float((1 << bit_depth) - 1)
    shots = list(shots)
    report = QualityReport()
    missing = [s.file for s in shots if s.key not in captured]
    if missing:
        report.findings.append(
            Finding(
                "error",
                "missing",
                tuple(missing),
                f"{len(missing)} of {len(shots)} frames were never captured",
                "run `rig-agent resume` to capture the missing frames",
            )
        )
    present = [s for s in shots if s.key in captured]
    darks = {s.exposure: load(s).astype(np.float64) for s in present if s.kind == "dark"}
    frames = _Signals(present, load, darks)
    for shot in present:
        if shot.kind != "dark":
            raw = load(shot)
            _exposure_checks(report, shot, raw, frames.subtract_dark(shot, raw), full, limits)
    _fringe_checks(report, present, frames, full, limits)
    _moved_check(report, present, frames, full, limits)
    return report


class _Signals:
    """Dark-subtracted frames (float64) by shot key, read on demand, never all at once."""

    def __init__(self, shots: list[Shot], load: Loader, darks: dict[float, np.ndarray]):
        self._shots = {s.key: s for s in shots if s.kind != "dark"}
        self._load, self._darks = load, darks

    def __contains__(self, key: str) -> bool:
        return key in self._shots

    def __getitem__(self, key: str) -> np.ndarray:
        shot = self._shots[key]
        return self.subtract_dark(shot, self._load(shot))

    def subtract_dark(self, shot: Shot, raw: np.ndarray) -> np.ndarray:
        return raw.astype(np.float64) - _dark_for(self._darks, shot.exposure, raw.shape)


def _dark_for(darks: dict[float, np.ndarray], exposure: float, shape) -> np.ndarray:
    if not darks:
        return np.zeros(shape)
    # The spec's rule: the same exposure, else the nearest in ratio, the shorter on a tie.
    best = min(darks, key=lambda e: (abs(np.log(e / exposure)), e))
    return darks[best]


def _exposure_checks(report, shot, raw, signal, full, limits) -> None:
    saturated = float(np.mean(raw >= full))
    if saturated > limits.saturated_fraction:
        report.findings.append(
            Finding(
                "error",
                "saturation",
                (shot.file,),
                f"{saturated:.1%} of the pixels are saturated in a {shot.kind} frame "
                f"at azimuth {shot.azimuth_deg:g}°",
                f"lower `exposure.{shot.kind}` in the plan (or the lamp/projector brightness) "
                "and scan again",
            )
        )
    bright = float(np.percentile(signal, 99))
    if bright < limits.dark_level * full:
        report.findings.append(
            Finding(
                "error",
                "underexposed",
                (shot.file,),
                f"a {shot.kind} frame at azimuth {shot.azimuth_deg:g}° is nearly black "
                f"(99th percentile {bright / full:.1%} of full scale)",
                "check that the light source and projector are on and aimed at the tablet; "
                f"raise `exposure.{shot.kind}` in the plan",
            )
        )


def _fringe_sets(shots: list[Shot]) -> dict[tuple, dict[float, Shot]]:
    sets: dict[tuple, dict[float, Shot]] = {}
    for s in shots:
        if s.kind == "fringe" and s.role == "bundle":
            sets.setdefault((s.azimuth_deg, s.period_um), {})[s.phase_deg % 360] = s
    return sets


def _fringe_checks(report, shots, frames, full, limits) -> None:
    low, drifting = [], []
    for (azimuth, period), steps in sorted(_fringe_sets(shots).items()):
        if sorted(steps) != [0, 90, 180, 270] or not all(s.key in frames for s in steps.values()):
            continue  # incomplete: already reported as missing
        i0, i90, i180, i270 = (frames[steps[p].key] for p in (0, 90, 180, 270))
        mean = (i0 + i90 + i180 + i270) / 4
        lit = mean > limits.lit_fraction * full
        if lit.sum() < 16:
            continue  # nothing lit: the exposure checks report it
        amplitude = 0.5 * np.hypot(i0 - i180, i90 - i270)
        modulation = float(np.median(amplitude[lit] / mean[lit]))
        drift = _relative_rms(i0 + i180, i90 + i270, lit, limits.bin_px)
        names = tuple(steps[p].file for p in (0, 90, 180, 270))
        report.figures[f"modulation_a{azimuth:g}_p{period:g}"] = modulation
        report.figures[f"drift_a{azimuth:g}_p{period:g}"] = drift
        if modulation < limits.min_modulation:
            low.append((names, azimuth, period, modulation))
        if drift > limits.max_drift:
            drifting.append((names, azimuth, period, drift))
    for names, azimuth, period, modulation in low:
        report.findings.append(
            Finding(
                "error",
                "modulation",
                names,
                f"the fringes at azimuth {azimuth:g}°, period {period:g} µm are too faint "
                f"(median modulation {modulation:.2f}, need {limits.min_modulation:.2f})",
                "focus the projector on the tablet, darken the room, or remove this "
                "period from the plan if the projector cannot resolve it",
            )
        )
    for names, azimuth, period, drift in drifting:
        report.findings.append(
            Finding(
                "error",
                "moved",
                names,
                f"the four phase steps at azimuth {azimuth:g}°, period {period:g} µm do not "
                f"agree (drift {drift:.1%}): the tablet or the light moved during the set",
                "check that the tablet rests firmly and the table is not bumped; scan again",
            )
        )


def _moved_check(report, shots, frames, full, limits) -> None:
    checks = [s for s in shots if s.role == "check" and s.key in frames]
    for check in checks:
        first = next(
            (
                s
                for s in shots
                if s.role == "bundle"
                and s.light_key() == check.light_key()
                and s.target == check.target
                and s.key in frames
            ),
            None,
        )
        if first is None:
            continue
        a, b = frames[first.key], frames[check.key]
        lit = a > limits.lit_fraction * full
        if lit.sum() < 16:
            continue
        scale = float(np.sum(a[lit] * b[lit]) / np.sum(a[lit] ** 2))
        moved = _relative_rms(scale * a, b, lit, limits.bin_px)
        report.figures["moved_relative_rms"] = moved
        if moved > limits.max_moved:
            report.findings.append(
                Finding(
                    "error",
                    "moved",
                    (first.file, check.file),
                    f"the tablet seems to have moved during the scan: the same light at the start "
                    f"and at the end gives images that differ by {moved:.1%} (RMS)",
                    "make sure the tablet rests firmly and nothing touched it; scan again",
                )
            )
