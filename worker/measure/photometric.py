"""Stages 1–3 from a bundle: flat-fielded shading, photometric normals, colour."""

from __future__ import annotations

import cv2
import numpy as np

from worker.measure.frames import angle_key
from worker.measure.result import Measurements
from worker.recon.color import rgb_reflectance
from worker.recon.ground_mask import stack_peak
from worker.recon.parallel import run_blocks
from worker.recon.photometric import light_directions, photometric_stereo
from worker.recon.radiometry import flat_field

__all__ = [
    "decode_with_references",
    "flat_fielded_shading",
    "measure_color",
    "measure_photometric",
]

# Width of the neighbourhood whose majority light set the fringe path's normals are fitted
# from (0: off), and the spread of the window's normals (± degrees about their mean) beyond
# which each pixel keeps its own set. Without the stand-down 5 px raised native-random-6's
# height MAE (2.65 → 2.85 µm, wedge depth 10.98 → 12.98; session 7, 10 scans), whose loss
# sits where the normals turn. bench/robustness.py, 25 scans: at 10° the MAE fell on 8 scans
# by more than 1 % and rose on one (native-paper-like, 0.391 → 0.395 µm); at 12° random-6
# lost as without (2.83 µm, 12.40); at 8° random-0's gain was gone (docs/benchmarks.md,
# issue 15, session 8).
_CONSENSUS_WINDOW_PX = 5
_CONSENSUS_MAX_TURN_DEG = 10.0


def _source_footprint(ref_stack, frames, height_um, pixel_size_um, workers=1):
    """Reference radiance at p′ = p − h·tanθ·u instead of p (in place; frames in threads).

    The light that reaches the surface point above p crossed the reference plane at p′
    (SCAN_BUNDLE.md): with a non-uniform source the flat field must be read there, or the
    shading of each light is off by E(p′)/E(p), a few per cent per millimetre of height,
    which tilts the normals by about a degree.
    """
    rows, cols = height_um.shape
    # Pixel coordinates as a row and a column, broadcast (the same maps as full grids).
    r = np.arange(rows, dtype=np.float32)[:, None]
    c = np.arange(cols, dtype=np.float32)[None, :]
    # Frames of one source direction (the colour channels of an azimuth) share their maps.
    sources: dict[tuple[float, float], list[int]] = {}
    for k, f in enumerate(frames):
        sources.setdefault((float(f.polar_deg), float(f.azimuth_deg)), []).append(k)
    groups = list(sources.items())

    def shift_frames(g: int) -> None:
        (polar_deg, azimuth_deg), ks = groups[g]
        shift = height_um * np.float32(np.tan(np.radians(polar_deg)) / pixel_size_um)
        phi = np.radians(azimuth_deg)
        # map = grid − shift·(sin φ, cos φ), the products computed into the map arrays.
        map_x = np.multiply(shift, np.float32(np.sin(phi)))
        np.subtract(c, map_x, out=map_x)
        shift *= np.float32(np.cos(phi))
        map_y = np.subtract(r, shift, out=shift)
        for k in ks:
            ref_stack[k] = cv2.remap(
                ref_stack[k],
                map_x,
                map_y,
                interpolation=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )

    run_blocks(shift_frames, range(len(groups)), workers=workers)
    return ref_stack


def decode_with_references(bundle, frames) -> tuple[np.ndarray, np.ndarray | None]:
    """Radiance of the frames and of their reference frames (None unless every frame has one)."""
    refs = [bundle.reference_of(f) for f in frames]
    if not all(r is not None for r in refs):
        return bundle.radiance_many(frames), None
    both = bundle.radiance_many([*frames, *refs])
    return both[: len(frames)], both[len(frames) :]


def _shading(bundle, frames, stack, rho_ref, meas, kind, ref_stack=None, workers=1):
    refs = [bundle.reference_of(f) for f in frames]
    if all(r is not None for r in refs):
        polar = np.array([f.polar_deg for f in frames], np.float64)
        if ref_stack is None:
            ref_stack = bundle.radiance_many(refs)
        if meas.rough_height_um is not None:
            ref_stack = _source_footprint(
                ref_stack, frames, meas.rough_height_um, meas.pixel_size_um, workers
            )
        return flat_field(
            stack, ref_stack, reference_reflectance=rho_ref, polar_deg=polar, workers=workers
        )
    meas.warnings.append(
        f"{kind}: no reference frames; assuming uniform illumination, albedo is relative"
    )
    # Without a flat field: L ∝ ρ·E·max(0, n·l) with E the same for every source (a source
    # of another power says so by its frame's exposure, which radiance is divided by), so
    # s = L / (bright level), one scale for all frames: their ratios carry the normals.  No
    # cos θ: that is the reference target's n·l, not the object's.
    scale = float(np.nanpercentile(stack, 99.5)) or 1.0
    return (stack / np.float32(scale)).astype(np.float32)


def flat_fielded_shading(
    bundle, frames, stack, rho_ref, *, ref_stack=None, height_um=None, pixel_size_um=None
) -> tuple[np.ndarray, list[str]]:
    """The shading of `frames` as the photometric stage computes it (flat-fielded by their
    reference frames, read where the light crossed the reference plane above `height_um`),
    and the warnings it gave; for stages that run after a reconstruction (worker.photos)."""
    meas = Measurements(pixel_size_um=float(pixel_size_um or 1.0), shape=stack.shape[1:])
    meas.rough_height_um = height_um
    shading = _shading(bundle, frames, stack, rho_ref, meas, "photometric", ref_stack)
    return shading, meas.warnings


def measure_photometric(bundle, photo, meas, rho_ref, *, stacks=None, workers: int = 1):
    """Normals, albedo and residual from the photometric frames `photo`.

    stacks: their radiance and their references' (`decode_with_references`), if decoded
    already; workers: threads of the photometric fit.
    """
    stack, ref_stack = stacks if stacks is not None else (bundle.radiance_many(photo), None)
    shading = _shading(bundle, photo, stack, rho_ref, meas, "photometric", ref_stack, workers)
    del stack, ref_stack, stacks
    az = np.array([f.azimuth_deg for f in photo])
    polar = np.array([f.polar_deg for f in photo])
    lights = light_directions(az, polar)
    alone = meas.fringe_height_um is None
    if alone:
        # No heights to tell the object from its ground: the dark-ground mask's evidence.
        meas.photometric_peak = stack_peak(shading)
    # Without fringe heights nothing corrects the normals afterwards: least squares where
    # it explains every lit sample, the robust fit elsewhere (never worse than least squares
    # on a matte object). With fringes the fusion's bias correction and weights were tuned
    # with the robust fit everywhere, and keep it; there each pixel's normal is then fitted
    # again from its neighbourhood's majority light set where the neighbourhood's normals
    # agree (photometric_fit.consensus_refit, see _CONSENSUS_WINDOW_PX).
    res = photometric_stereo(
        shading,
        lights,
        least_squares_when_consistent=alone,
        consensus_window_px=0 if alone else _CONSENSUS_WINDOW_PX,
        consensus_max_turn_deg=_CONSENSUS_MAX_TURN_DEG,
        workers=workers,
    )
    meas.normals = res.normals
    meas.albedo = res.albedo
    meas.residual = res.residual
    meas.lights_used = res.lights_used
    meas.photometric_outliers = res.outliers
    meas.photometric_consensus = res.consensus
    meas.photometric_polar_deg = float(np.median(polar))
    meas.used["photometric_azimuths_deg"] = sorted({angle_key(a) for a in az})


def measure_color(bundle, color, meas, rho_ref, *, stacks=None):
    """Linear RGB reflectance from the colour frames `color` given the normals; stacks as
    for `measure_photometric`."""
    if meas.normals is None:
        meas.warnings.append("color: frames ignored (no normals to divide the shading by)")
        return
    stack, ref_stack = stacks if stacks is not None else (bundle.radiance_many(color), None)
    shading = _shading(bundle, color, stack, rho_ref, meas, "color", ref_stack)
    del stack, ref_stack, stacks
    az = np.array([f.azimuth_deg for f in color])
    polar = np.array([f.polar_deg for f in color])
    res = rgb_reflectance(
        shading,
        [f.channel for f in color],
        light_directions(az, polar),
        meas.normals,
        fallback_albedo=meas.albedo,
    )
    meas.rgb_linear = res.rgb
    meas.used["color_azimuths_deg"] = sorted({angle_key(a) for a in az})
    meas.used["color_channels"] = sorted({f.channel for f in color})
