"""Reference matching and fringe-set rules, against a brute-force reading of the spec."""

from __future__ import annotations

import numpy as np
import pytest

from worker.bundle import Frame
from worker.bundle.matching import (
    angles_equal,
    check_frames,
    fringe_sets,
    reference_map,
    reference_of,
    same_lighting,
)


def _fringe(index, phase, *, target="object", azimuth=30.0, period=400.0, polar=40.0) -> Frame:
    return Frame(
        index=index, file=f"f{index}.png", kind="fringe", target=target,
        azimuth_deg=azimuth, polar_deg=polar, period_um=period, phase_deg=phase,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("a", "b", "equal"),
    [
        (0.0, 360.0, True),
        (-90.0, 270.0, True),
        (359.9999995, 0.0, True),
        (0.0, 720.000001, True),
        (10.0, 10.000002, False),
        (None, None, True),
        (None, 0.0, False),
    ],
)
def test_angles_modulo_360(a, b, equal) -> None:
    assert angles_equal(a, b) is equal
    assert angles_equal(b, a) is equal


def test_fringe_set_rules() -> None:
    good = [_fringe(i, p) for i, p in enumerate((0, 90, 180, 270))]
    assert check_frames(good) == []
    wrapped = [_fringe(i, p) for i, p in enumerate((360, 90, -180, 270.0000004))]
    assert check_frames(wrapped) == []
    three = good[:3]
    assert "holds 3" in check_frames(three)[0].message
    five = [*good, _fringe(4, 0)]
    problems = check_frames(five)
    assert [p.where for p in problems] == ["frames[0]"] and "holds 5" in problems[0].message
    doubled = [*good[:3], _fringe(3, 0)]
    assert "missing phases: 270" in check_frames(doubled)[0].message
    # A different period, azimuth, polar angle or target makes a different set.
    for change in ({"period": 800.0}, {"azimuth": 31.0}, {"polar": 41.0}, {"target": "reference"}):
        split = [*good[:3], _fringe(3, 270, **change)]
        assert len(fringe_sets(split)) == 2
        fringe_problems = [p for p in check_frames(split) if "fringe set" in p.message]
        assert [p.where for p in fringe_problems] == ["frames[0]", "frames[3]"]


def test_duplicate_files_are_reported() -> None:
    frames = [_fringe(i, p) for i, p in enumerate((0, 90, 180, 270))]
    frames[2] = Frame(**{**frames[2].__dict__, "file": "f0.png"})
    problems = check_frames(frames)
    assert [str(p) for p in problems] == [
        "frames[2].file: 'f0.png' is already named by frames[0]; "
        "each image is named by exactly one frame"
    ]


def _random_frames(rng: np.random.Generator, n: int) -> list[Frame]:
    """Frames on a coarse grid plus jitter of ±1e-6-ish, so near-misses and wrap-arounds occur."""
    frames = []
    for i in range(n):
        kind = rng.choice(["photometric", "color", "fringe"])
        jitter = rng.choice([0.0, 4e-7, -4e-7, 3e-6, 360.0, -360.0])
        frames.append(
            Frame(
                index=i, file=f"{i}.png", kind=str(kind),
                target=str(rng.choice(["object", "reference"])),
                azimuth_deg=float(rng.choice([0.0, 90.0, 359.9999997])) + float(jitter),
                polar_deg=float(rng.choice([30.0, 30.0000009])),
                channel=str(rng.choice(["red", "green"])) if kind == "color" else None,
                period_um=float(rng.choice([100.0, 100.0000005])) if kind == "fringe" else None,
                phase_deg=float(rng.choice([0.0, 90.0, 450.0])) if kind == "fringe" else None,
            )
        )  # fmt: skip
    return frames


def test_indexed_reference_map_equals_brute_force() -> None:
    rng = np.random.default_rng(11)
    for _ in range(20):
        frames = _random_frames(rng, 40)
        fast = reference_map(frames)
        for frame in frames:
            brute = reference_of(frame, frames)
            assert fast.get(frame.index) == brute
            if brute is not None:
                assert same_lighting(frame, brute)


def test_reference_rule_needs_every_object_frame_but_not_darks() -> None:
    dark = Frame(index=0, file="d.png", kind="dark")
    obj = [_fringe(i + 1, p) for i, p in enumerate((0, 90, 180, 270))]
    ref = [_fringe(i + 5, p, target="reference") for i, p in enumerate((0, 90, 180, 270))]
    assert check_frames([dark, *obj]) == []  # no reference frames at all: fine
    assert check_frames([dark, *obj, *ref]) == []
    photometric = Frame(index=9, file="p.png", kind="photometric", azimuth_deg=0.0, polar_deg=40.0)
    problems = check_frames([dark, *obj, *ref, photometric])
    assert [p.where for p in problems] == ["frames[9]"]
    assert "has no reference frame" in problems[0].message
