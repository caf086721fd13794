"""Hostile variants of a simulated bundle, written in place (tests only).

Each changes the frames as an instrument the spec allows would, without telling the manifest:
a projector whose modulation transfer falls with the period, light scattered inside the clay.
Frames are edited in their own encoding (the simulator writes linear 16-bit PNGs, gamma 1).
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

__all__ = ["fringe_sets", "projector_mtf", "clay_scatter", "drop_frames"]


def fringe_sets(bundle_dir: Path) -> dict[tuple, list[dict]]:
    """Fringe frames of the manifest by (target, azimuth, period), each set's 4 frames."""
    manifest = json.loads((Path(bundle_dir) / "manifest.json").read_text())
    sets: dict[tuple, list[dict]] = defaultdict(list)
    for f in manifest["frames"]:
        if f["kind"] == "fringe":
            key = (f.get("target", "object"), f["azimuth_deg"], round(f["period_um"], 3))
            sets[key].append(f)
    return sets


def _edit_set(bundle_dir: Path, frames: list[dict], edit) -> None:
    paths = [Path(bundle_dir) / f["file"] for f in frames]
    raw = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in paths]
    dtype = raw[0].dtype
    stack = np.stack(raw).astype(np.float64)
    mean = stack.mean(axis=0)
    out = edit(stack, mean)
    top = np.iinfo(dtype).max
    for p, img in zip(paths, out, strict=True):
        cv2.imwrite(str(p), np.clip(np.rint(img), 0, top).astype(dtype))


def projector_mtf(bundle_dir: Path, *, sigma_um: float) -> None:
    """Scale each fringe set's modulation by a Gaussian projector MTF exp(−2π²σ²/P²), object
    and reference alike (the projector's optics, not the camera: geometry stays sharp)."""
    for (_, _, period), frames in fringe_sets(bundle_dir).items():
        gain = float(np.exp(-2 * np.pi**2 * sigma_um**2 / period**2))
        _edit_set(bundle_dir, frames, lambda st, mean, g=gain: mean + g * (st - mean))


def clay_scatter(bundle_dir: Path, *, sigma_px: float) -> None:
    """Blur the fringe pattern's relative modulation on the object by a Gaussian of σ px
    (light entering the clay and leaving it elsewhere); the reference target is matte."""
    for (target, _, _), frames in fringe_sets(bundle_dir).items():
        if target != "object":
            continue

        def edit(st, mean):
            rel = (st - mean) / np.maximum(mean, 1.0)
            blurred = np.stack([cv2.GaussianBlur(r, (0, 0), sigma_px) for r in rel])
            return mean + mean * blurred

        _edit_set(bundle_dir, frames, edit)


def drop_frames(bundle_dir: Path, keep) -> None:
    """Rewrite the manifest with only the frames for which keep(frame) is true."""
    path = Path(bundle_dir) / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["frames"] = [f for f in manifest["frames"] if keep(f)]
    path.write_text(json.dumps(manifest))
