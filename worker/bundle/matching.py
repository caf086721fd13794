"""Cross-frame rules of SCAN_BUNDLE.md: reference matching, fringe sets, one frame per file.

"An object frame's reference frame is the one with the same kind, azimuth, polar angle,
channel, period and phase (angles compared modulo 360°, numbers equal within 1e-6)."
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

from worker.bundle.errors import Problem
from worker.bundle.manifest import Frame

TOLERANCE = 1e-6
FRINGE_PHASES_DEG = (0.0, 90.0, 180.0, 270.0)


def angles_equal(a_deg: float | None, b_deg: float | None) -> bool:
    """Equal modulo 360° within 1e-6 degrees; two Nones are equal."""
    if a_deg is None or b_deg is None:
        return a_deg is None and b_deg is None
    d = (a_deg - b_deg) % 360.0
    return min(d, 360.0 - d) <= TOLERANCE


def numbers_equal(a: float | None, b: float | None) -> bool:
    """Equal within 1e-6; two Nones are equal."""
    if a is None or b is None:
        return a is None and b is None
    return abs(a - b) <= TOLERANCE


def same_lighting(a: Frame, b: Frame) -> bool:
    """The spec's matching rule: same kind, azimuth, polar angle, channel, period and phase."""
    return (
        a.kind == b.kind
        and a.channel == b.channel
        and angles_equal(a.azimuth_deg, b.azimuth_deg)
        and angles_equal(a.polar_deg, b.polar_deg)
        and numbers_equal(a.period_um, b.period_um)
        and angles_equal(a.phase_deg, b.phase_deg)
    )


class _ToleranceIndex:
    """Finds items whose key equals a query key within the tolerance, in O(1) per lookup.

    A key is a tuple of parts ``(mode, value)``: mode "exact" (compared with ==), "number"
    (within 1e-6) or "angle" (within 1e-6 modulo 360). Continuous values are put on a grid
    of cell 1e-5 > 1e-6, so a match lies in the same or a neighbouring cell; the candidates
    are then checked exactly. This keeps hostile bundles with 10^5 frames from costing N².
    """

    _CELL = 1e-5
    _ANGLE_CELLS = round(360.0 / _CELL)

    def __init__(self) -> None:
        self._cells: dict[tuple, list[tuple[tuple, object]]] = {}

    def _cell(self, mode: str, value) -> int | object:
        if mode == "exact" or value is None:
            return value
        if mode == "angle":
            return math.floor((value % 360.0) / self._CELL) % self._ANGLE_CELLS
        return math.floor(value / self._CELL)

    def _neighbours(self, mode: str, value) -> list:
        cell = self._cell(mode, value)
        if mode == "exact" or value is None:
            return [cell]
        if mode == "angle":
            return [(cell + d) % self._ANGLE_CELLS for d in (-1, 0, 1)]
        return [cell - 1, cell, cell + 1]

    def add(self, key: tuple, item: object) -> None:
        cell = tuple(self._cell(mode, value) for mode, value in key)
        self._cells.setdefault(cell, []).append((key, item))

    def find(self, key: tuple) -> list:
        """Items added with a key equal to ``key`` within tolerance, in insertion order."""
        found = []
        for cell in itertools.product(*(self._neighbours(m, v) for m, v in key)):
            for other, item in self._cells.get(cell, ()):
                if all(_part_equal(a, b) for a, b in zip(key, other, strict=True)):
                    found.append(item)
        return found


def _part_equal(a: tuple, b: tuple) -> bool:
    mode, x = a
    y = b[1]
    if mode == "exact":
        return x == y
    return angles_equal(x, y) if mode == "angle" else numbers_equal(x, y)


def lighting_key(frame: Frame) -> tuple:
    """Key of the matching rule: kind, azimuth, polar angle, channel, period and phase."""
    return (
        ("exact", frame.kind),
        ("exact", frame.channel),
        ("angle", frame.azimuth_deg),
        ("angle", frame.polar_deg),
        ("number", frame.period_um),
        ("angle", frame.phase_deg),
    )


def reference_map(frames: Sequence[Frame]) -> dict[int, Frame]:
    """``{object frame index: its reference frame}`` (the first match in manifest order)."""
    index = _ToleranceIndex()
    for frame in frames:
        if frame.target == "reference":
            index.add(lighting_key(frame), frame)
    out: dict[int, Frame] = {}
    for frame in frames:
        if frame.target == "object":
            found = index.find(lighting_key(frame))
            if found:
                out[frame.index] = min(found, key=lambda f: f.index)
    return out


def reference_of(frame: Frame, frames: Sequence[Frame]) -> Frame | None:
    """The first reference frame lit like ``frame`` (object frames only), else None."""
    if frame.target != "object":
        return None
    for other in frames:
        if other.target == "reference" and same_lighting(frame, other):
            return other
    return None


def fringe_sets(frames: Sequence[Frame]) -> list[list[Frame]]:
    """Fringe frames grouped by (target, azimuth, polar angle, period), in manifest order."""
    groups: list[list[Frame]] = []
    index = _ToleranceIndex()
    for frame in frames:
        if frame.kind != "fringe":
            continue
        key = (
            ("exact", frame.target),
            ("angle", frame.azimuth_deg),
            ("angle", frame.polar_deg),
            ("number", frame.period_um),
        )
        found = index.find(key)
        if found:
            groups[min(found)].append(frame)
        else:
            index.add(key, len(groups))
            groups.append([frame])
    return groups


def _fringe_set_problem(group: list[Frame]) -> str | None:
    remaining = list(FRINGE_PHASES_DEG)
    extra = []
    for frame in group:
        hit = next((p for p in remaining if angles_equal(frame.phase_deg, p)), None)
        if hit is None:
            extra.append(frame)
        else:
            remaining.remove(hit)
    if len(group) == 4 and not remaining and not extra:
        return None
    f = group[0]
    listed = ", ".join(f"frames[{g.index}] ({g.phase_deg:g}°)" for g in group[:8])
    listed += ", ..." if len(group) > 8 else ""
    missing = ", ".join(f"{p:g}" for p in remaining) or "none"
    return (
        f"fringe set (target {f.target}, azimuth {f.azimuth_deg:g}°, polar {f.polar_deg:g}°, "
        f"period {f.period_um:g} µm) must hold exactly four frames at phases 0, 90, 180, 270°; "
        f"it holds {len(group)}: {listed}; missing phases: {missing}"
    )


def check_frames(frames: Sequence[Frame]) -> list[Problem]:
    """Problems with the set of frames: shared files, fringe sets, missing reference frames.

    Dark frames need no reference frame: they carry no lighting to match.
    """
    problems: list[Problem] = []
    first_by_file: dict[str, int] = {}
    for frame in frames:
        if frame.file in first_by_file:
            problems.append(
                Problem(
                    f"frames[{frame.index}].file",
                    f"{frame.file!r} is already named by frames[{first_by_file[frame.file]}]; "
                    "each image is named by exactly one frame",
                )
            )
        else:
            first_by_file[frame.file] = frame.index
    for group in fringe_sets(frames):
        message = _fringe_set_problem(group)
        if message:
            problems.append(Problem(f"frames[{group[0].index}]", message))
    if any(f.target == "reference" for f in frames):
        references = reference_map(frames)
        for frame in frames:
            lit_object = frame.target == "object" and frame.kind != "dark"
            if lit_object and frame.index not in references:
                problems.append(
                    Problem(
                        f"frames[{frame.index}]",
                        "has no reference frame (same kind, azimuth, polar angle, channel, "
                        "period and phase) although the bundle holds reference frames",
                    )
                )
    return problems
