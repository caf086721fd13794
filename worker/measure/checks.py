"""Bundles that conform to SCAN_BUNDLE.md yet cannot be reconstructed: say what is wrong.

Each check raises `ReconstructionError` with a message naming the culprit (the CLI exits 2
with it) instead of letting a stage fail with a traceback or write a surface of noise.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from worker.measure.result import ReconstructionError
from worker.recon.arrays import fast_median
from worker.recon.photometric import light_directions

__all__ = [
    "check_lights",
    "check_reference_periods",
    "check_saturation",
    "check_surface_request",
    "measured_period_px",
]

# Smallest singular value of the unit light directions over the largest: below it the lights
# do not span 3-D (all one azimuth, or one azimuth and its opposite at one polar angle), and
# no normal is determined (`photometric.photometric_stereo` needs three independent ones).
_MIN_LIGHT_SPREAD = 0.05
_SATURATED_SHARE = 0.5
_PERIOD_TOLERANCE = 0.25


def check_surface_request(frames, *, surface: str) -> None:
    """A baseline surface needs its kind of frame: `fringe` needs object fringe sets with
    their reference frames, `normals` at least 3 photometric object frames."""
    obj = [f for f in frames if f.target == "object"]
    if surface == "fringe":
        refs = [f for f in frames if f.kind == "fringe" and f.target == "reference"]
        if not any(f.kind == "fringe" for f in obj) or not refs:
            raise ReconstructionError(
                "surface 'fringe' asked, but the bundle has no fringe sets with reference "
                "frames (object and reference fringe frames are both needed)"
            )
    if surface == "normals" and sum(f.kind == "photometric" for f in obj) < 3:
        raise ReconstructionError(
            "surface 'normals' asked, but the bundle has fewer than 3 photometric object frames"
        )


def check_lights(frames) -> None:
    """The photometric object frames' light directions must span 3-D (when there are ≥ 3)."""
    photo = [f for f in frames if f.target == "object" and f.kind == "photometric"]
    if len(photo) < 3:
        return
    dirs = light_directions([f.azimuth_deg for f in photo], [f.polar_deg for f in photo])
    sv = np.linalg.svd(dirs, compute_uv=False)
    if sv[-1] < _MIN_LIGHT_SPREAD * sv[0]:
        azimuths = sorted({round(f.azimuth_deg % 360, 3) for f in photo})
        polars = sorted({round(f.polar_deg, 3) for f in photo})
        raise ReconstructionError(
            f"photometric frames: the {len(photo)} lights do not span 3-D (azimuths "
            f"{azimuths}°, polar angles {polars}°); photometric stereo needs at least three "
            "non-coplanar light directions, e.g. three or more azimuths"
        )


def check_saturation(bundle, frames, *, sample: int = 6) -> None:
    """Fail when every sampled object frame is mostly at the top code (over-exposed): up to
    `sample` frames evenly spread over the object's non-dark frames are decoded."""
    obj = [f for f in frames if f.target == "object" and f.kind != "dark"]
    if not obj:
        return
    top = 2 ** int(bundle.manifest.camera.bit_depth) - 1
    picks = [obj[i] for i in np.unique(np.linspace(0, len(obj) - 1, sample).round().astype(int))]

    def share(frame) -> float | None:
        raw = bundle.raw(frame)
        if raw.dtype.kind == "f":  # linear radiance: no top code
            return None
        return float(np.count_nonzero(raw >= top)) / raw.size

    # Decoded two at a time (the reader is thread-safe; PNG decoding releases the GIL):
    # the check runs before anything else, with the second core idle.
    with ThreadPoolExecutor(max_workers=2) as pool:
        shares = list(pool.map(share, picks))
    if any(v is None for v in shares):
        return
    if min(shares) >= _SATURATED_SHARE:
        raise ReconstructionError(
            f"object frames saturated: in each of {len(picks)} sampled frames at least "
            f"{100 * min(shares):.0f} % of the pixels are at the top code {top} "
            f"(bit depth {bundle.manifest.camera.bit_depth}); shorten the exposure"
        )


def measured_period_px(phase_rad: np.ndarray, *, row_step: int = 4) -> float:
    """Period (px) of a wrapped fringe phase map: 2π over the length of its median phase
    gradient (wrapped neighbour differences along rows and columns, central half).

    Every `row_step`-th row of the central half and the row below it are read: a check
    with a 25 % tolerance needs no more than ~80,000 differences, and the whole half (with
    complex exponentials to wrap them) cost ~35 ms per set at 1.3 Mpx."""
    p = np.asarray(phase_rad, np.float32)
    rows, cols = p.shape
    r0, r1, c0, c1 = rows // 4, rows - rows // 4, cols // 4, cols - cols // 4
    top = p[r0 : r1 - 1 : row_step, c0:c1]
    below = p[r0 + 1 : r1 : row_step, c0:c1][: top.shape[0]]
    fx = _median_wrapped(top[:, 1:] - top[:, :-1])
    fy = _median_wrapped(below - top)
    f = np.hypot(fx, fy)
    return float(2 * np.pi / f) if f > 0 else float("inf")


def _median_wrapped(d: np.ndarray) -> float:
    """Median of phase differences wrapped to [−π, π] (NaN ignored; NaN when none)."""
    two_pi = np.float32(2 * np.pi)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return float("nan")
    d -= two_pi * np.rint(d / two_pi)
    return float(fast_median(d))


def check_reference_periods(found: list[tuple[float, float, float]]) -> None:
    """The reference target's fringe sets must show the periods their manifest entries give.

    found: (azimuth°, nominal period px, measured period px) of reference sets whose nominal
    period lies between 3 px and half the frame (measurable by `measured_period_px`). When
    most of them are off by more than 25 %, the reference frames do not belong to these
    entries (another session's, or shuffled) and every phase difference would be noise.
    """
    if not found:
        return
    off = [(az, nom, got) for az, nom, got in found if not abs(got / nom - 1) <= _PERIOD_TOLERANCE]
    if len(off) * 2 > len(found):
        az, nom, got = off[0]
        raise ReconstructionError(
            f"reference fringe frames do not match their manifest entries: {len(off)} of "
            f"{len(found)} checked sets show another period (e.g. azimuth {az:g}°: "
            f"{got:.1f} px measured where the manifest gives {nom:.1f} px)"
        )
