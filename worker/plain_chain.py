"""`--fusion plain`: a scan bundle → the model directory by the textbook chain.

`reconstruct_plain(bundle_path, out_dir, *, progress=None) -> report`. The floor every
default reconstruction must clear (issue 14): radiance as SCAN_BUNDLE.md defines it
(`worker.bundle`), flat field by the reference frames where they exist, least-squares
photometric stereo over the lit samples, 4-step fringe phase with temporal unwrapping and
heights averaged over the azimuths, one screened-Poisson solve with fixed weights
(`worker.recon.plain`), written by `worker.model_dir` like the default. Nothing here is
estimated from the scan's noise or tuned per scan.

A bundle that cannot be reconstructed raises `ReconstructionError` (the CLI exits 2) and
leaves OUTDIR untouched.
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Callable

import numpy as np

from worker.bundle import open_bundle
from worker.measure.frames import angle_key
from worker.measure.fringe import fringe_sets
from worker.measure.photometric import decode_with_references
from worker.measure.result import ReconstructionError, bundle_errors_as_reconstruction_errors
from worker.model_dir import ModelArrays, write_model_dir_timed
from worker.recon.color import grey_reflectance, linear_to_srgb8, rgb_reflectance
from worker.recon.fringe import four_step_phase
from worker.recon.height import height_from_phase
from worker.recon.photometric import light_directions
from worker.recon.plain import (
    MIN_MODULATION,
    ORDER_RESIDUAL_MAX,
    SHADOW_FRACTION,
    average_azimuths_um,
    fringe_weight,
    fuse_plain_um,
    least_squares_normals,
    normals_from_height,
    plain_mask,
)
from worker.recon.radiometry import flat_field
from worker.recon.unwrap import phase_difference, temporal_unwrap

__all__ = ["SURFACES", "reconstruct_plain"]

SURFACES = ("fused", "fringe", "normals")

Progress = Callable[[str, float], None]

# An azimuth's height further than this fraction of the finest period's height equivalent
# P/tanθ (one wrong fringe order) from the azimuths' median is dropped before averaging.
OUTLIER_ORDERS = 0.25
# Fringe heights are kept where at least this many azimuths agree (fewer if the bundle has
# fewer azimuths): the other pixels are reached by the normals or the membrane.
MIN_AGREEING_AZIMUTHS = 2


def _noop(stage: str, fraction: float) -> None:
    return None


def reconstruct_plain(
    bundle_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    surface: str = "fused",
    progress: Progress | None = None,
) -> dict:
    """Reconstruct a scan bundle by the plain chain into `out_dir`; returns the report.

    surface: "fused" (normals and fringe heights, whichever the bundle has), or a baseline
    of the same chain: "fringe" (the fringe heights alone) or "normals" (the normals
    integrated alone, at the fringe heights' median level when there are any).
    progress(stage, fraction): fraction of the whole job done, 0…1.
    """
    if surface not in SURFACES:
        raise ValueError(f"surface must be one of {SURFACES}, got {surface!r}")
    report_progress = progress or _noop
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    with bundle_errors_as_reconstruction_errors(), open_bundle(bundle_path) as bundle:
        model, report = _reconstruct(bundle, surface, timings, report_progress)
    return write_model_dir_timed(
        out_dir, model, report, timings=timings, started_s=t_start, progress=report_progress
    )


def _reconstruct(bundle, surface, timings: dict, progress: Progress) -> tuple[ModelArrays, dict]:
    man = bundle.manifest
    cam = man.camera
    s = float(cam.pixel_size_um)
    rho_ref = float(man.reference.reflectance)
    obj = [f for f in bundle.frames if f.target == "object"]
    counts: dict[str, int] = defaultdict(int)
    for f in bundle.frames:
        counts[f.kind if f.target == "object" else f"reference_{f.kind}"] += 1
    warnings: list[str] = []
    used: dict = {"frames": dict(counts)}

    t0 = time.perf_counter()
    progress("photometric", 0.05)
    photo = [f for f in obj if f.kind == "photometric"]
    normals = albedo = lights_used = None
    if len(photo) >= 3:
        shading, saturated = _shading(bundle, photo, rho_ref, warnings, "photometric")
        lights = light_directions([f.azimuth_deg for f in photo], [f.polar_deg for f in photo])
        normals, albedo, lights_used = least_squares_normals(shading, lights, saturated=saturated)
        del shading, saturated
        if not np.isfinite(albedo).any():
            warnings.append("photometric: no pixel has 3 lit, unsaturated samples; no normals")
            normals = albedo = lights_used = None
        else:
            used["photometric_azimuths_deg"] = sorted({angle_key(f.azimuth_deg) for f in photo})
    elif photo:
        warnings.append(
            f"photometric: {len(photo)} object frame(s), at least 3 are needed; no normals"
        )
    timings["photometric"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress("fringe", 0.30)
    fringe = _fringe_heights(bundle, [f for f in obj if f.kind == "fringe"], rho_ref, warnings)
    fringe_h = brightness_f = None
    if fringe is not None:
        fringe_h, brightness_f, used["fringe"] = fringe
    timings["fringe"] = time.perf_counter() - t0
    if normals is None and fringe_h is None:
        raise ReconstructionError(
            "bundle: nothing to reconstruct (needs ≥ 3 photometric object frames with lit, "
            "unsaturated pixels, or fringe sets with reference frames); frames found: "
            + (", ".join(f"{k}={v}" for k, v in sorted(counts.items())) or "none")
        )

    t0 = time.perf_counter()
    progress("mask", 0.70)
    measured = np.zeros((cam.height, cam.width), bool)
    if normals is not None:
        measured |= np.isfinite(normals[..., 2])
    if fringe_h is not None:
        measured |= np.isfinite(fringe_h)
    brightness = albedo if albedo is not None else brightness_f
    mask = plain_mask(brightness, measured)
    if mask.sum() < 16:
        raise ReconstructionError(
            "mask: no tablet found (no pixel is both bright enough and measured); "
            "is the tablet in the frame and lit?"
        )
    timings["mask"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress("fusion", 0.75)
    use_n = normals if surface != "fringe" or fringe_h is None else None
    use_f = fringe_h if surface != "normals" or normals is None else None
    height = fuse_plain_um(use_n, use_f, mask, pixel_size_um=s)
    if use_f is None and fringe_h is not None:
        # Normals fix the shape only; the absolute level is the fringes' (median offset).
        both = mask & np.isfinite(height) & np.isfinite(fringe_h)
        if both.any():
            height += np.float32(np.median(fringe_h[both] - height[both]))
    mask &= np.isfinite(height)
    out_normals = normals_from_height(np.where(mask, height, np.nan), pixel_size_um=s)
    timings["fusion"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress("color", 0.85)
    color = [f for f in obj if f.kind == "color"]
    rgb = None
    if color and normals is not None:
        c_shading, _ = _shading(bundle, color, rho_ref, warnings, "color")
        c_lights = light_directions([f.azimuth_deg for f in color], [f.polar_deg for f in color])
        rgb = rgb_reflectance(
            c_shading, [f.channel for f in color], c_lights, normals, fallback_albedo=albedo
        ).rgb
        used["color_channels"] = sorted({f.channel for f in color})
    elif color:
        warnings.append("color: frames ignored (no normals to divide the shading by)")
    if rgb is None:
        rgb = grey_reflectance(np.nan_to_num(brightness, nan=0.0))
    albedo8 = linear_to_srgb8(np.where(mask[..., None], rgb, 0))
    timings["color"] = time.perf_counter() - t0

    used_surface = (
        "fused"
        if use_n is not None and use_f is not None
        else ("normals" if use_n is not None else "fringe")
    )
    quality: dict[str, np.ndarray] = {}
    figures: dict = {
        "tablet_pixels": int(mask.sum()),
        "tablet_fraction_of_image": float(mask.mean()),
    }
    if lights_used is not None:
        quality["lights_used"] = np.where(mask, lights_used, 0).astype(np.int16)
        if fringe_h is None:  # photographs alone: the measured normals, as the default's
            quality["photometric_normals"] = np.where(mask[..., None], normals, np.nan).astype(
                np.float32
            )
        figures["normal_coverage"] = float(np.isfinite(normals[..., 2])[mask].mean())
    if fringe_h is not None:
        d = np.where(mask, fringe_h - height, np.nan).astype(np.float32)
        quality["fringe_disagreement_um"] = d
        figures["fringe_coverage"] = float(np.isfinite(fringe_h)[mask].mean())
        finite = np.isfinite(d)
        figures["median_abs_disagreement_um"] = (
            float(np.median(np.abs(d[finite]))) if finite.any() else None
        )
    report = {
        "format": "digital-hammurabi-model",
        "version": 1,
        "scan": {
            "id": man.scan.id,
            "face": man.scan.face,
            "pose": None if man.scan.pose is None else [list(map(float, r)) for r in man.scan.pose],
        },
        "pixel_size_um": s,
        "image_size": {"width": int(cam.width), "height": int(cam.height)},
        "fusion": "plain",
        "surface": used_surface,
        "used": used
        | {
            "fringe_weight": fringe_weight(s),
            "shadow_fraction": SHADOW_FRACTION,
            "min_modulation": MIN_MODULATION,
        },
        "warnings": warnings,
        "quality": figures,
    }
    model = ModelArrays(
        height_um=height,
        normals=out_normals,
        albedo_srgb8=albedo8,
        mask=mask,
        pixel_size_um=s,
        quality=quality,
    )
    return model, report


def _shading(bundle, frames, rho_ref: float, warnings: list, kind: str):
    """Flat-fielded shading (K, H, W) of the frames and where a sample (or its reference)
    is saturated (K, H, W) bool. Without reference frames: radiance over its 99.5th
    percentile, one scale for all frames (sources of unequal power say so by `exposure`)."""
    stack, ref_stack = decode_with_references(bundle, frames)
    saturated = _saturated(bundle, frames, stack)
    if ref_stack is not None:
        refs = [bundle.reference_of(f) for f in frames]
        saturated |= _saturated(bundle, refs, ref_stack)
        polar = np.array([f.polar_deg for f in frames], np.float64)
        shading = flat_field(stack, ref_stack, reference_reflectance=rho_ref, polar_deg=polar)
        return shading, saturated
    warnings.append(f"{kind}: no reference frames; assuming uniform illumination")
    unsat = stack[~saturated]
    scale = float(np.percentile(unsat, 99.5)) if unsat.size else 1.0
    return stack / np.float32(scale if scale > 0 else 1.0), saturated


def _saturated(bundle, frames, radiance: np.ndarray) -> np.ndarray:
    """(K, H, W) bool: the stored value was the camera's full scale 2^bit_depth − 1.

    From the radiance: lin(v) = L·exposure + lin(v_dark) reaches lin(full scale − ½) only at
    full scale. Float32 TIFF frames are linear radiance with no full scale: never saturated.
    """
    cam = bundle.manifest.camera
    full = float(2**cam.bit_depth - 1)
    threshold = np.float32(((full - 0.5) / full) ** float(cam.response_gamma))
    out = np.zeros(radiance.shape, bool)
    darks: dict[int, np.ndarray] = {}
    for k, f in enumerate(frames):
        if bundle.image_info(f).is_float:
            continue
        lin = radiance[k] * np.float32(f.exposure)
        dark = bundle.dark_of(f)
        if dark is not None:
            if dark.index not in darks:
                # A dark frame's radiance is lin(v_dark) / its exposure.
                darks[dark.index] = bundle.radiance(dark) * np.float32(dark.exposure)
            lin += darks[dark.index]
        out[k] = lin >= threshold
    return out


def _fringe_heights(bundle, fringe, rho_ref: float, warnings: list):
    """(heights averaged over azimuths (H, W) µm, brightness (H, W), report entry) or None."""
    if not fringe:
        return None
    sets = fringe_sets(bundle, fringe, warnings)
    if not sets:
        warnings.append("fringe: no usable fringe set; no heights")
        return None
    heights, outlier_um, brightness = [], [], None
    summary = {}
    for (azimuth, polar), levels in sets.items():
        wrapped, mods = [], []
        ratio = None
        for i, (_, frames, refs) in enumerate(levels):
            stack = bundle.radiance_many([*frames, *refs])
            o, r = four_step_phase(stack[:4]), four_step_phase(stack[4:])
            wrapped.append(phase_difference(o.phase_rad, r.phase_rad))
            mods.append(np.fmin(o.modulation, r.modulation))
            if i == 0:
                with np.errstate(invalid="ignore", divide="ignore"):
                    # Mean level relative to the white target: ρ·max(0, n·l)/cos θ.
                    ratio = np.where(r.mean > 0, o.mean / r.mean * np.float32(rho_ref), np.nan)
        periods = np.array([p for p, _, _ in levels])
        un = temporal_unwrap(
            np.stack(wrapped), periods, modulation=np.stack(mods), min_modulation=MIN_MODULATION
        )
        del wrapped, mods
        h = height_from_phase(un.dpsi_rad, period_um=float(periods[-1]), polar_deg=polar)
        bad = ~np.isfinite(h) | ~(un.order_residual <= ORDER_RESIDUAL_MAX)
        h[bad] = np.nan
        heights.append(h)
        outlier_um.append(OUTLIER_ORDERS * periods[-1] / np.tan(np.radians(polar)))
        brightness = ratio if brightness is None else np.fmax(brightness, ratio)
        summary[f"{azimuth:g}"] = {
            "periods_um": [float(p) for p in periods],
            "kept": round(float(np.isfinite(h).mean()), 4),
        }
    # Two azimuths must agree where the bundle has two (SCAN_BUNDLE.md's standard
    # acquisition has four); a bundle of one fringe azimuth has nothing to cross-check.
    mean, _ = average_azimuths_um(
        np.stack(heights),
        outlier_um=float(min(outlier_um)),
        min_azimuths=min(MIN_AGREEING_AZIMUTHS, len(heights)),
    )
    if not np.isfinite(mean).any():
        warnings.append("fringe: no pixel has a fringe height")
        return None
    return mean, brightness.astype(np.float32), {"azimuths": summary}
