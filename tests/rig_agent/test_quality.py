"""Quality checks on synthetic frames with known faults."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from rig_agent.patterns import ProjectorGeometry
from rig_agent.plan import Shot, expand, quick_plan
from rig_agent.quality import Thresholds, check_scan

H, W, BITS = 48, 64, 12
FULL = 2**BITS - 1
SIGMA = 8.0  # read noise, levels
GEOMETRY = ProjectorGeometry(width=W, height=H, pixel_size_um=100.0)
SHOTS = expand(quick_plan(), GEOMETRY, target="object")


def albedo(shift_px: int = 0) -> np.ndarray:
    rng = np.random.default_rng(7)
    texture = gaussian_filter(rng.normal(size=(H, W + 8)), 2.0)
    texture = 0.3 + 0.6 * (texture - texture.min()) / np.ptp(texture)
    texture[:, :12] = texture[:, -12:] = 0.02  # a tablet on black velvet: it has an outline
    return texture[:, 4 + shift_px : 4 + shift_px + W]


def render(shot: Shot, *, shift_px: int = 0, modulation: float = 0.7, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed + shot.index)
    dark = 60.0
    if shot.kind == "dark":
        signal = np.zeros((H, W))
    else:
        signal = 2400.0 * albedo(shift_px)
        if shot.kind == "fringe":
            phi = np.radians(shot.azimuth_deg)
            y, x = np.mgrid[0:H, 0:W] * 100.0
            phase = 2 * np.pi * (np.sin(phi) * x + np.cos(phi) * y) / shot.period_um
            signal = signal * (1 + modulation * np.cos(phase + np.radians(shot.phase_deg))) / 2
    noisy = dark + signal + rng.normal(0, SIGMA, size=(H, W))
    return np.clip(np.rint(noisy), 0, FULL).astype(np.uint16)


def run(frames: dict[str, np.ndarray], captured=None, thresholds=None):
    return check_scan(
        SHOTS,
        lambda s: frames[s.key],
        captured=set(frames) if captured is None else captured,
        bit_depth=BITS,
        thresholds=thresholds,
    )


@pytest.fixture
def good() -> dict[str, np.ndarray]:
    return {s.key: render(s) for s in SHOTS}


def test_a_good_scan_passes(good):
    report = run(good)
    assert report.ok and report.findings == []
    # Modulation estimate: noise σ=8 on a fringe amplitude of ~0.7·A with A ≳ 360 levels biases
    # B/A by at most ~σ²/(B·A) ≈ 1e-3 — far below the tolerance of 0.03.
    mods = [v for k, v in report.figures.items() if k.startswith("modulation")]
    assert mods and all(abs(m - 0.7) < 0.03 for m in mods)
    # Check frame vs first on 4×4 tiles: √2·σ/(4·mean) ≈ 1.4·8/(4·1440) ≈ 0.2 % from noise.
    assert report.figures["moved_relative_rms"] < 0.01
    assert "passed" in report.to_text()


def test_saturated_frame_is_named(good):
    shot = next(s for s in SHOTS if s.kind == "photometric")
    good[shot.key] = np.minimum(good[shot.key] * 3, FULL).astype(np.uint16)
    report = run(good)
    assert not report.ok
    (finding,) = [f for f in report.findings if f.check == "saturation"]
    assert finding.frames == (shot.file,) and "exposure.photometric" in finding.advice


def test_black_frame_is_underexposed(good):
    shot = next(s for s in SHOTS if s.kind == "color")
    good[shot.key] = render(SHOTS[0])  # the dark frame's content: no light
    (finding,) = [f for f in run(good).findings if f.check == "underexposed"]
    assert finding.frames == (shot.file,)


def test_faint_fringes_are_reported_per_set(good):
    faint = [
        s
        for s in SHOTS
        if s.kind == "fringe"
        and s.azimuth_deg == 90
        and s.period_um
        == max(t.period_um for t in SHOTS if t.kind == "fringe" and t.azimuth_deg == 90)
    ]
    for s in faint:
        good[s.key] = render(s, modulation=0.02)
    (finding,) = [f for f in run(good).findings if f.check == "modulation"]
    assert set(finding.frames) == {s.file for s in faint}
    assert "focus the projector" in finding.advice


def test_a_tablet_moved_between_phase_steps(good):
    # Noise alone: 2σ/(b·2·mean A) ≈ 2·8/(4·2·720) ≈ 0.3 % on 4×4 tiles. A 3-pixel shift of
    # the tablet in two of the four steps moves its outline: 4–8 % on the coarse periods
    # (on fine periods the fringe weights of the residual average out within a tile).
    fringe = [s for s in SHOTS if s.kind == "fringe" and s.azimuth_deg == 0]
    for s in fringe:
        if s.phase_deg in (180, 270):
            good[s.key] = render(s, shift_px=3)
    report = run(good)
    moved = [f for f in report.findings if f.check == "moved"]
    assert moved and all(f.frames[0].startswith("object/") for f in moved)
    assert {f.frames for f in moved} <= {
        tuple(s.file for s in fringe if s.period_um == p) for p in {s.period_um for s in fringe}
    }


def test_a_tablet_moved_between_start_and_end(good):
    check = SHOTS[-1]
    good[check.key] = render(check, shift_px=3)
    report = run(good)
    (finding,) = [f for f in report.findings if f.check == "moved"]
    assert finding.frames[1] == check.file
    assert "moved" in report.to_text()


def test_missing_frames(good):
    gone = SHOTS[5]
    report = run(good, captured=set(good) - {gone.key})
    (finding,) = [f for f in report.findings if f.check == "missing"]
    assert finding.frames == (gone.file,) and "rig-agent resume" in finding.advice
    assert "FAILED" in report.to_text()


def test_thresholds_are_respected(good):
    report = run(good, thresholds=Thresholds(min_modulation=0.9))
    assert not report.ok and all(f.check == "modulation" for f in report.findings)


def test_bad_bit_depth():
    with pytest.raises(ValueError, match="bit_depth"):
        check_scan(SHOTS, lambda s: None, captured=set(), bit_depth=0)
