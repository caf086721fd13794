"""Bundle → reconstruction → model directory (stages 1–8 of the reconstruction issue).

`reconstruct_bundle(bundle_path, out_dir, *, fusion="default", progress=None) -> report`.
The measurement stages (photometric stereo, colour, fringe heights) are in
`worker.measure`; this module chooses the surface, builds the mask, fuses, and writes the
model directory atomically. A bundle that cannot be reconstructed raises
`ReconstructionError` (the CLI exits 2) and leaves OUTDIR untouched.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait

import cv2
import numpy as np
from scipy import ndimage

from worker.bundle import open_bundle
from worker.measure import Measurements, ReconstructionError, measure_bundle
from worker.measure.checks import check_lights, check_saturation, check_surface_request
from worker.measure.result import bundle_errors_as_reconstruction_errors
from worker.model_dir import ModelArrays, albedo_png_bytes, write_model_dir_timed
from worker.recon.arrays import fast_median
from worker.recon.band_wiener import BAND_SCALES_PX, band_wiener_correct, fringe_noise_colour
from worker.recon.color import linear_to_srgb8
from worker.recon.fusion import (
    PIXEL_AREA_VAR_PX2,
    fuse_default,
    point_sample_sigma_px,
    sharpen_heights,
)
from worker.recon.fusion_paper import fuse_paper
from worker.recon.ground_mask import ground_mask
from worker.recon.height import (
    GUARD_CLIFF,
    GUARD_FRINGE,
    GUARD_NEIGHBOURHOOD,
    fill_holes,
    guard_heights,
    valid_fringe,
)
from worker.recon.integrate import integrate_normals
from worker.recon.mask import tablet_mask
from worker.recon.normal_bias import correct_normal_bias
from worker.recon.quality import (
    NORMAL_FLOOR_RAD,
    crease_sigma_um,
    fringe_blur_px,
    fringe_sigma_um,
    normal_sigma_rad,
    tilt_bias_rad,
)
from worker.recon.walls import check_refinement, refine_cliffs, unmeasured_jumps

__all__ = [
    "FUSIONS",
    "SURFACES",
    "ReconstructionError",
    "camera_blur_px",
    "camera_psf",
    "reconstruct_bundle",
    "refine_walls",
    "refine_walls_checked",
    "surface_of",
]

FUSIONS = ("default", "paper", "plain")
SURFACES = ("fused", "fringe", "normals")
Progress = Callable[[str, float], None]


def _noop(stage: str, fraction: float) -> None:
    return None


def reconstruct_bundle(
    bundle_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    fusion: str = "default",
    surface: str = "fused",
    progress: Progress | None = None,
) -> dict:
    """Reconstruct a scan bundle into the model directory `out_dir`; returns the report.

    fusion: "default" (weighted least squares), "paper" (Kumar et al. 2003 §3.3) or "plain"
    (the textbook chain of `worker.plain_chain`, the floor the default must clear).
    surface: "fused" (normal use), or a baseline: "fringe" (5×5 median of the fringe
    heights) or "normals" (normals integrated alone), for the benchmark.
    progress(stage, fraction): fraction of the whole job done, 0…1.
    """
    if fusion not in FUSIONS:
        raise ValueError(f"fusion must be one of {FUSIONS}, got {fusion!r}")
    if surface not in SURFACES:
        raise ValueError(f"surface must be one of {SURFACES}, got {surface!r}")
    if fusion == "plain":  # the textbook floor, a chain of its own (worker.plain_chain)
        from worker.plain_chain import reconstruct_plain

        return reconstruct_plain(bundle_path, out_dir, surface=surface, progress=progress)
    report_progress = progress or _noop
    t_start = time.perf_counter()
    with bundle_errors_as_reconstruction_errors(), open_bundle(bundle_path) as bundle:
        check_surface_request(bundle.frames, surface=surface)
        check_lights(bundle.frames)
        check_saturation(bundle, bundle.frames)
        meas = measure_bundle(bundle, progress=report_progress, color_in_background=True)
        try:
            model, report, timings = _model(
                meas,
                camera_psf(bundle.manifest),
                fusion=fusion,
                surface=surface,
                progress=report_progress,
            )
        finally:
            # The colour stage decodes its frames in the background (`_model` waits for
            # it, unless it failed first): the bundle is closed after it.
            futures_wait(meas.pending)
    report = write_model_dir_timed(
        out_dir, model, report, timings=timings, started_s=t_start, progress=report_progress
    )
    return report


def _model(
    meas: Measurements,
    psf: tuple[float, str],
    *,
    fusion: str,
    surface: str,
    progress: Progress,
) -> tuple[ModelArrays, dict, dict]:
    """Mask, surface, cliff refinement, quality maps and report from the measurements: the
    model directory's arrays, its report and the stage timings (seconds, filled in further
    by the caller). psf: the camera's (σ px, its source), `camera_psf`."""
    blur_px, blur_source = psf
    timings = dict(meas.timings)
    t0 = time.perf_counter()
    progress("mask", 0.80)
    mask = _mask(meas)
    if mask.sum() < 16:
        raise ReconstructionError(
            "mask: no tablet found (no pixel is both bright enough and measured); "
            "is the tablet in the frame and lit?"
        )
    timings["mask"] = time.perf_counter() - t0

    walls_flag = None
    with ThreadPoolExecutor(max_workers=1) as side:
        # What depends on the mask alone is prepared beside the fusion, whose solves leave a
        # core idle (it waits for the colour stage first). The fusion keeps the mask unless
        # a height comes out NaN, checked below.
        side_mask = mask.copy()
        prepared = side.submit(_mask_products, meas, side_mask)
        t0 = time.perf_counter()
        progress("fusion", 0.84)
        height, normals_of, used_surface, refinements = _surface(
            meas, mask, fusion=fusion, surface=surface, blur_sigma_px=blur_px
        )
        if used_surface == "default":
            # The normals are those of the fused surface before its cliff pixels are refined
            # (`surface_of`): they are computed beside the refinement.
            with ThreadPoolExecutor(max_workers=1) as pool:
                normals_job = pool.submit(normals_of)
                timings["fusion"] = time.perf_counter() - t0
                t0 = time.perf_counter()
                before_walls = height
                height, refinements["walls"] = refine_walls_checked(
                    meas, height, mask, blur_sigma_px=blur_px
                )
                # Where the refinement acted, for the viewer's trust map (worker/trust.py).
                walls_flag = np.isfinite(height) & (height != before_walls)
                normals = normals_job.result()
            timings["walls"] = time.perf_counter() - t0
        else:
            normals = normals_of()
            timings["fusion"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        blur = refinements.get("fringe_blur", {}).get("sigma_px", 0.0)
        crease = refinements.get("fringe_blur", {}).pop("_crease", None)
        decided = refinements.get("walls", {}).pop("_decided", None)
        height, normals, guard_flag, refinements["guard"] = _guard(
            meas,
            height,
            normals,
            mask,
            fringe_blur_px=blur,
            cliff_decided=decided,
            crease_um=crease,
        )
        timings["guard"] = time.perf_counter() - t0
        on_mask = prepared.result()  # after the colour stage (re-raising its errors)
    if "color" in meas.timings:
        timings["color"] = meas.timings["color"]
    measured_mask = mask
    mask = mask & np.isfinite(height)
    if not np.array_equal(mask, side_mask):
        on_mask = _mask_products(meas, mask)

    quality = _quality_maps(meas, height, mask, on_mask.quality)
    if guard_flag is not None:
        # On the mask as measured: a pixel the guard left NaN is off the model's mask,
        # and its flag says why.
        quality["guard"] = np.where(measured_mask, guard_flag, 0).astype(np.uint8)
    if walls_flag is not None:
        quality["walls"] = (mask & walls_flag).astype(np.uint8)
    report = _report(meas, mask, quality, on_mask.figures, fusion=fusion, surface=used_surface)
    report["refinements"] = refinements
    if "photometric_consensus" in quality:
        report["refinements"]["light_set_consensus"] = {
            "pixels": int(np.count_nonzero(quality["photometric_consensus"])),
            "map": "quality/photometric_consensus.npy",
        }
    report["quality"]["camera_blur_sigma_px"] = blur_px
    report["quality"]["camera_blur_source"] = blur_source
    report["quality"]["reference_modulation_by_period"] = _reference_modulation(meas)

    report["timings_s"] = timings
    model = ModelArrays(
        height_um=height,
        normals=normals,
        albedo_srgb8=on_mask.albedo_srgb8,
        mask=mask,
        pixel_size_um=meas.pixel_size_um,
        quality=quality,
        albedo_png=on_mask.albedo_png,
    )
    return model, report, timings


def _reference_modulation(meas: Measurements) -> dict[str, float]:
    """Median B/A of the reference target per fringe period (µm) of the first azimuth: the
    projector's and the camera's modulation transfer together, reported, not used."""
    return {f"{k[2]:.6g}": float(v) for k, v in sorted(meas.reference_modulation.items())}


def _mask(meas: Measurements) -> np.ndarray:
    has_n = _has_normal(meas.normals) if meas.normals is not None else None
    if meas.fringe_height_um is None and meas.photometric_peak is not None:
        # Photographs alone: the object on its dark ground, from the stack of lit images.
        found = ground_mask(meas.photometric_peak, has_normal=has_n)
        meas.used["mask"] = {
            "method": "dark ground (recon.ground_mask)",
            # None where no ground class was found (report.json is strict JSON).
            "ground_level": found.ground_level if np.isfinite(found.ground_level) else None,
            "noise_sigma": found.ground_sigma if np.isfinite(found.ground_sigma) else None,
            "stood_down": found.stood_down,
        }
        if found.stood_down is not None:
            meas.warnings.append(
                f"mask: no dark ground found ({found.stood_down}); every measured pixel is kept"
            )
        return found.mask
    has_h = np.isfinite(meas.fringe_height_um) if meas.fringe_height_um is not None else None
    brightness = meas.albedo
    return tablet_mask(
        brightness,
        has_normal=has_n,
        has_height=has_h,
        modulation=meas.modulation,
        height_um=meas.fringe_height_um,
        pixel_size_um=meas.pixel_size_um,
    )


def _has_normal(normals: np.ndarray) -> np.ndarray:
    """(H, W) bool: all three components finite (component by component: numpy's
    reduction over the length-3 last axis is ~20× slower)."""
    return (
        np.isfinite(normals[..., 0]) & np.isfinite(normals[..., 1]) & np.isfinite(normals[..., 2])
    )


def camera_blur_px(bundle) -> float:
    """σ (px) of the camera's PSF: `camera.psf_sigma_px` of the manifest, 0 when absent.

    Not measured from the data: the one evidence a bundle carries about blur, the fringe
    modulation that falls at fine periods, is as much the projector's optics (its pixel grid,
    defocus) and light scattered inside the clay as the camera's, and SCAN_BUNDLE.md says so
    (on a bundle with a 0.5 px camera and a defocused projector the former fit read 2.96 px
    and the sharpening it drove left wedges 40 µm too deep). A blur nobody measured is
    assumed absent: an unsharpened wedge is a little shallow, a wrongly sharpened one is
    wrong by far more.
    """
    return camera_psf(bundle.manifest)[0]


def camera_psf(manifest) -> tuple[float, str]:
    """(σ px, where it came from) of the camera's PSF for a parsed manifest."""
    sigma = manifest.camera.psf_sigma_px
    if sigma is None:
        return 0.0, "assumed 0: camera.psf_sigma_px absent (not inferred from fringe modulation)"
    return float(sigma), "manifest camera.psf_sigma_px"


def surface_of(
    meas: Measurements,
    mask: np.ndarray,
    *,
    fusion: str = "default",
    surface: str = "fused",
    blur_sigma_px: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Heights (H, W) µm and normals (H, W, 3) of the chosen surface on the mask, and its name.

    Uses what the bundle has: normals and fringe heights → fusion; normals only →
    integration; fringe heights only → the heights, with normals from their gradient.
    blur_sigma_px: σ of the camera's PSF (`camera_blur_px`); the default fusion's heights
    are sharpened by it and the pixel's own area (`fusion.point_sample_sigma_px`,
    `fusion.sharpen_heights`), the baselines are left as measured.
    """
    h, normals_of, name, _ = _surface(
        meas, mask, fusion=fusion, surface=surface, blur_sigma_px=blur_sigma_px
    )
    return h, normals_of(), name


def _surface(
    meas: Measurements,
    mask: np.ndarray,
    *,
    fusion: str = "default",
    surface: str = "fused",
    blur_sigma_px: float = 0.0,
) -> tuple[np.ndarray, Callable[[], np.ndarray], str, dict]:
    """`surface_of`, with the normals as a function to call (the pipeline computes them
    beside the cliff refinement), and the report of each refinement: where it acted."""
    s = meas.pixel_size_um
    has_n = meas.normals is not None
    has_f = meas.fringe_height_um is not None and np.isfinite(meas.fringe_height_um[mask]).any()
    if surface == "fringe" or (has_f and not has_n):
        h = _fringe_surface(meas.fringe_height_um, mask)
        return h, lambda: _normals_from_height(h, mask, s), "fringe", {}
    if surface == "normals" or not has_f:
        h = integrate_normals(meas.normals, pixel_size_um=s, mask=mask)
        if has_f:
            # Normals fix the shape only; the absolute level is the fringes' (median offset).
            h += np.float32(np.nanmedian(meas.fringe_height_um[mask] - h[mask]))
        return h, lambda: _unit_normals(meas.normals, h, mask, s), "normals", {}
    sig_n = normal_sigma_rad(meas.residual, meas.lights_used, polar_deg=meas.photometric_polar_deg)
    sig_f, sigma_f = fringe_sigma_um(meas.fringe_height_um, mask, azimuths_used=meas.azimuths_used)
    fringe_blur = fringe_blur_px(meas.fringe_height_um, meas.normals, mask, pixel_size_um=s)
    crease = crease_sigma_um(meas.normals, pixel_size_um=s, blur_px=fringe_blur)
    sig_f = np.sqrt(np.square(sig_f) + np.square(crease)).astype(np.float32)
    if fusion == "paper":
        sig_n_typ = float(np.median(sig_n[mask & np.isfinite(sig_n)]))
        h, _ = fuse_paper(
            meas.normals,
            meas.fringe_height_um,
            pixel_size_um=s,
            mask=mask,
            normal_sigma_rad=sig_n_typ,
            height_sigma_um=sigma_f,
        )
        return h, lambda: _unit_normals(meas.normals, h, mask, s), "paper", {}
    # The normals' bias by steepness, which their residual does not show, measured against
    # the fringe heights and added to their σ (`quality.tilt_bias_rad`).
    tilt_bias = tilt_bias_rad(meas.normals, meas.fringe_height_um, mask, pixel_size_um=s)
    sig_n = np.sqrt(np.square(sig_n) + np.square(tilt_bias)).astype(np.float32)
    # The normals' low-frequency bias is taken out by the fringe heights first.
    normals = correct_normal_bias(
        meas.normals,
        meas.fringe_height_um,
        pixel_size_um=s,
        mask=mask,
        height_sigma_um=sig_f,
        floor_rad=NORMAL_FLOOR_RAD,
    )
    h = fuse_default(
        normals,
        meas.fringe_height_um,
        pixel_size_um=s,
        mask=mask,
        normal_sigma_rad=sig_n,
        height_sigma_um=sig_f,
        workers=min(2, os.cpu_count() or 1),
    )
    # Scale by scale, the fringe heights correct what the normals' bias left in the fused
    # surface, where they disagree beyond the fringes' noise measured at that scale.
    h, band_entry = _band_wiener(
        meas, h, mask, crease=crease, fringe_blur=fringe_blur, camera_psf_px=blur_sigma_px
    )
    refinements = {
        # "_crease" (popped by the pipeline before the report is written): the same map the
        # guard needs (the measured normals and this blur), not computed twice.
        "fringe_blur": {"sigma_px": fringe_blur, "_crease": crease},
        "tilt_bias": {
            "pixels": int(np.count_nonzero(mask & (tilt_bias > 0))),
            "max_mrad": float(1000 * tilt_bias[mask].max()) if mask.any() else 0.0,
        },
        "normal_bias": _normal_bias_entry(meas.normals, normals, mask),
        "band_wiener": band_entry,
    }
    # The heights are those of the surface averaged over each pixel and the camera's PSF;
    # the output is the point sample at the pixel's centre (SCAN_BUNDLE.md).
    sharpen_px = point_sample_sigma_px(blur_sigma_px)
    sharp = sharpen_heights(h, mask, blur_sigma_px=sharpen_px, pixel_size_um=s)
    refinements["sharpen"] = {
        "sigma_px": sharpen_px,
        "camera_psf_px": float(blur_sigma_px),
        "pixel_area_var_px2": PIXEL_AREA_VAR_PX2,
        "pixels": int(np.count_nonzero(mask & (sharp != h) & np.isfinite(h))),
    }
    h = sharp
    return h, lambda: _unit_normals(meas.normals, h, mask, s), "default", refinements


def _band_wiener(
    meas: Measurements,
    h: np.ndarray,
    mask: np.ndarray,
    *,
    crease: np.ndarray,
    fringe_blur: float,
    camera_psf_px: float,
) -> tuple[np.ndarray, dict]:
    """`band_wiener.band_wiener_correct` with the fringe noise's colour measured on the
    azimuths' differences; unchanged (and reported as not run) without per-azimuth heights
    or the fringes' phase noise. Returns (heights, report entry: per band its scales, the
    noise's colour κ, the mean gain and the share of tablet pixels where it acted)."""
    if meas.fringe_azimuth_heights_um is None or meas.fringe_sigma_um is None:
        return h, {"ran": False}
    colour = fringe_noise_colour(meas.fringe_azimuth_heights_um, meas.fringe_azimuth_sigma_um, mask)
    # The fringe heights' blur relative to the surface's point samples: theirs relative to
    # the normals, plus what blurs both (the camera's PSF and the pixel's own area).
    resolution = float(np.hypot(fringe_blur, point_sample_sigma_px(camera_psf_px)))
    band = band_wiener_correct(
        h,
        meas.fringe_height_um,
        mask,
        noise_sigma_um=meas.fringe_sigma_um,
        crease_sigma_um=crease,
        colour=colour,
        blur_px=fringe_blur,
        resolution_px=resolution,
    )
    entry = {
        "ran": True,
        "resolution_px": round(resolution, 3),
        "scales_px": list(BAND_SCALES_PX),
        "noise_colour": [round(float(k), 3) for k in colour],
        "mean_gain": [round(g, 4) for g in band.mean_gain],
        "acting_share": [round(a, 4) for a in band.acting_share],
    }
    return band.height_um, entry


def _normal_bias_entry(measured: np.ndarray, corrected: np.ndarray, mask: np.ndarray) -> dict:
    """Where `correct_normal_bias` rotated the normals, and by how much (median, mrad). It
    acts everywhere or nowhere: it stands down when the disagreement is within the noise."""
    moved = mask & np.any(measured != corrected, axis=-1) & np.isfinite(corrected[..., 2])
    if not moved.any():
        return {"pixels": 0, "median_rotation_mrad": 0.0, "stood_down": True}
    dot = np.clip(np.sum(measured[moved] * corrected[moved], axis=-1), -1.0, 1.0)
    return {
        "pixels": int(moved.sum()),
        "median_rotation_mrad": float(1000 * np.median(np.arccos(dot))),
        "stood_down": False,
    }


def refine_walls(
    meas: Measurements, height: np.ndarray, mask: np.ndarray, *, blur_sigma_px: float
) -> np.ndarray:
    """`refine_walls_checked`'s heights alone (for the benches)."""
    return refine_walls_checked(meas, height, mask, blur_sigma_px=blur_sigma_px)[0]


def refine_walls_checked(
    meas: Measurements, height: np.ndarray, mask: np.ndarray, *, blur_sigma_px: float
) -> tuple[np.ndarray, dict]:
    """Heights of the pixels straddling a cliff set to the side their centre lies on (a
    point sample, SCAN_BUNDLE.md) from the fringe mixture of the two sides
    (`recon.walls.refine_cliff_heights`), kept region by region only where the sides'
    measured fringe heights bound them (`recon.walls.check_refinement`); unchanged without
    per-period fringe samples or photometric normals. Returns (heights, report entry); the
    entry's "_decided" (H, W) bool, popped by the pipeline before the report is written,
    holds the pixels whose side the fringe response decided (`_cliff_decided`)."""
    if not meas.cliff_samples or meas.normals is None or meas.fringe_height_um is None:
        return height, {"pixels": 0, "regions": 0, "stood_down_regions": 0, "ran": False}
    refinement, pure = refine_cliffs(
        height,
        meas.fringe_height_um,
        meas.normals,
        mask,
        meas.cliff_samples,
        pixel_size_um=meas.pixel_size_um,
        blur_sigma_px=blur_sigma_px,
    )
    refined = np.where(mask, refinement.height_um, height).astype(np.float32)
    check = check_refinement(height, refined, meas.fringe_height_um, mask)
    entry = {
        "pixels": int(check.acted.sum()),
        "regions": check.regions,
        "stood_down_regions": check.stood_down,
        "stood_down_pixels": check.stood_down_pixels,
        "ran": True,
    }
    with np.errstate(invalid="ignore"):
        stood_down = mask & ~(refined == height) & ~check.acted
    entry["_decided"] = _cliff_decided(refinement.fraction, pure, stood_down)
    return check.height_um, entry


# A share of the upper side within this of ½ does not tell the side of the pixel's centre:
# the shares scatter by ~0.05–0.1 between azimuths where a side is lit in each.
_SIDE_MARGIN = 0.1


def _cliff_decided(fraction, pure, stood_down):
    """Pixels whose side the fringe response decided: a share of the upper side clearly
    off ½ in a region the check kept, or a pure pixel's response."""
    with np.errstate(invalid="ignore"):
        sure = np.abs(fraction - np.float32(0.5)) >= _SIDE_MARGIN
    return (sure & ~stood_down) | pure


def _guard(
    meas: Measurements,
    height: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    fringe_blur_px: float = 0.0,
    cliff_decided: np.ndarray | None = None,
    crease_um: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """The last step of every surface with fringe heights (`height.guard_heights`): no
    height further than max(5σ, 50 µm) from the valid fringe heights, none outside its
    neighbourhood's range elsewhere; replaced pixels and their neighbours get the normals
    of the guarded surface. σ is the fringe height's uncertainty as a point sample: the
    phase noise (`Measurements.fringe_sigma_um`) and, in quadrature, how far a blurred or
    pixel-averaged height departs from the centre's at a crease (`quality.crease_sigma_um`
    with the fringes' measured blur) — without it the guard pulled wedge bottoms up to the
    blurred fringes (random physics seed 0: wedge depth error 14.9 → 25.3 µm). Returns
    heights, normals, the flag map (None without fringe heights: nothing to check against)
    and the report entry.

    cliff_decided: where the cliff refinement ran, the pixels whose side it decided
    (`refine_walls_checked`); the other pixels next to a jump without a valid fringe
    height (`walls.unmeasured_jumps`) are left NaN at a cliff (flag `GUARD_CLIFF`: a point
    sample on the wrong side, or between the two, is a spike of the cliff's height); on
    steep ground their normals explain the jump and they are kept (counted).

    crease_um: `quality.crease_sigma_um` of the measured normals with `fringe_blur_px`,
    when the caller has it already (the default fusion's); computed here otherwise."""
    if meas.fringe_height_um is None or not np.isfinite(meas.fringe_height_um[mask]).any():
        return height, normals, None, {"ran": False}
    sigma = meas.fringe_sigma_um
    if meas.normals is not None and sigma is not None:
        crease = crease_um
        if crease is None:
            crease = crease_sigma_um(
                meas.normals, pixel_size_um=meas.pixel_size_um, blur_px=fringe_blur_px
            )
        sigma = np.hypot(sigma, crease).astype(np.float32)
    valid = valid_fringe(
        meas.fringe_height_um,
        mask,
        azimuths_used=meas.azimuths_used,
        pixel_size_um=meas.pixel_size_um,
    )
    g = guard_heights(
        height,
        meas.fringe_height_um,
        sigma,
        mask,
        valid=valid,
        pixel_size_um=meas.pixel_size_um,
    )
    guarded, flag = g.height_um, g.flag
    cliff_px = steep_px = 0
    if cliff_decided is not None:
        jumps = unmeasured_jumps(
            guarded,
            meas.fringe_height_um,
            meas.normals,
            mask,
            cliff_decided,
            valid=valid,
            pixel_size_um=meas.pixel_size_um,
            # A cliff under twice the guard's floor leaves a mid value within the floor of
            # both sides: at fine pixels (26.8 µm: 2.6·s = 70 µm) wedge walls the normals
            # under-read were taken for cliffs (paper preset: 1,285 pixels, median error
            # 4 µm).
            min_jump_um=max(2.6 * meas.pixel_size_um, 2 * 50.0),
        )
        # Left NaN: filled from the neighbourhood, such a pixel takes a mid value, a spike
        # of half the cliff's height. Steep ground is kept: every height along it is a
        # point sample of it, bounded by its neighbourhood's range above.
        guarded = np.where(jumps.cliff, np.float32(np.nan), guarded).astype(np.float32)
        flag = np.where(jumps.cliff, np.uint8(GUARD_CLIFF), flag).astype(np.uint8)
        cliff_px, steep_px = int(jumps.cliff.sum()), int(jumps.steep.sum())
    entry = {
        "ran": True,
        "k_sigma": 5.0,
        "floor_um": 50.0,
        "valid_fringe_pixels": int(valid.sum()),
        "pixels_beyond_fringe_bound": int(np.count_nonzero(flag == GUARD_FRINGE)),
        "pixels_outside_neighbourhood": int(np.count_nonzero(flag == GUARD_NEIGHBOURHOOD)),
        "cliff_pixels_side_unknown": cliff_px,
        "steep_pixels_kept": steep_px,
    }
    if not flag.any():
        return height, normals, flag, entry
    near = cv2.dilate((flag > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    normals = normals.copy()
    rows, cols = np.nonzero(near & mask)
    normals[rows, cols] = _normals_at(guarded, mask, rows, cols, meas.pixel_size_um)
    return guarded, normals, flag, entry


def _normals_at(h, mask, rows, cols, s):
    """(N, 3) unit normals of the surface h at pixels (rows, cols): central differences,
    one-sided where a neighbour is off the mask, flat where both are (`_normals_from_height`
    at a few pixels, without its whole-frame distance transform)."""
    hp = np.pad(np.where(mask, h, np.nan), 1, constant_values=np.nan).astype(np.float64)
    r, c = rows + 1, cols + 1
    centre = hp[r, c]

    def slope(before, after):
        both = np.isfinite(before) & np.isfinite(after)
        g = np.where(both, (after - before) / (2 * s), 0.0)
        g = np.where(~both & np.isfinite(after), (after - centre) / s, g)
        g = np.where(~both & np.isfinite(before), (centre - before) / s, g)
        return np.nan_to_num(g)

    gx = slope(hp[r, c - 1], hp[r, c + 1])
    gy = slope(hp[r - 1, c], hp[r + 1, c])
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    return np.stack([-gx / norm, -gy / norm, -1.0 / norm], axis=-1).astype(np.float32)


def _fringe_surface(height_um, mask):
    h = np.where(mask, height_um, np.nan).astype(np.float32)
    finite = np.isfinite(h)
    if not finite.any():
        raise ReconstructionError("fringe frames: no pixel of the tablet has a fringe height")
    fill = float(np.median(h[finite]))
    # ndimage.median_filter(…, size=5, mode="nearest") by OpenCV (the same values, ~40× faster).
    padded = np.pad(np.where(finite, h, np.float32(fill)), 2, mode="edge")
    med = cv2.medianBlur(padded, 5)[2:-2, 2:-2]
    med = np.where(finite, med, np.nan)
    return np.where(mask, fill_holes(med, mask), np.nan).astype(np.float32)


def _normals_from_height(h, mask, s):
    """Unit normals of the surface h by central differences; off-surface neighbours are
    replaced by the nearest surface value so that the rim gets one-sided slopes, not cliffs."""
    finite = np.isfinite(h)
    if not finite.any():
        return np.full((*h.shape, 3), np.nan, np.float32)
    idx = ndimage.distance_transform_edt(~finite, return_distances=False, return_indices=True)
    filled = h[tuple(idx)]
    gy, gx = np.gradient(filled.astype(np.float64), s)
    # n = (−gx, −gy, −1)/‖·‖ component by component: the same values as dividing the stacked
    # (H, W, 3) vectors by np.linalg.norm (per pixel (gx² + gy²) + 1 in that order), without
    # its whole-frame float64 temporaries.
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    out = np.empty((*h.shape, 3), np.float32)
    for k, component in enumerate((gx, gy, np.ones_like(gx))):
        out[..., k] = np.where(mask, -component / norm, np.nan)
    return out


def _unit_normals(normals, h, mask, s):
    """The normals of the reconstructed surface h.

    Not the photometric normals themselves: the surface's gradient is their projection on
    integrable fields (plus the fringes' low frequencies), which removes the curl part of
    their noise; on the simulator's default noise it halves the median angular error.
    """
    return _normals_from_height(h, mask, s)


class _MaskProducts:
    """The outputs that depend on the tablet mask alone (`_mask_products`)."""

    def __init__(self, quality, figures, albedo_srgb8, albedo_png):
        self.quality = quality  # the quality maps but the fringe disagreement
        self.figures = figures  # the report's quality figures of those maps and the mask
        self.albedo_srgb8 = albedo_srgb8
        self.albedo_png = albedo_png


def _mask_products(meas: Measurements, mask: np.ndarray) -> _MaskProducts:
    """Quality maps, report figures and albedo texture (with its PNG) on the mask.

    Waits for the stages still running in the background (the colour)."""
    meas.finish()
    quality: dict[str, np.ndarray] = {}
    if meas.residual is not None:
        quality["photometric_residual"] = np.where(mask, meas.residual, np.nan).astype(np.float32)
        quality["lights_used"] = np.where(mask, meas.lights_used, 0).astype(np.int16)
        if meas.photometric_outliers is not None:
            # Lit samples the robust fit left out: highlights, interreflections, penumbrae.
            quality["photometric_outliers"] = np.where(mask, meas.photometric_outliers, 0).astype(
                np.int16
            )
        if meas.photometric_consensus is not None:
            # Where the normal was fitted from the neighbourhood's light set.
            quality["photometric_consensus"] = (mask & meas.photometric_consensus).astype(np.uint8)
        if meas.fringe_height_um is None:
            # Photographs alone: the measured normals themselves, the product that
            # photometric stereo is judged by (normals.npy holds the integrated surface's).
            quality["photometric_normals"] = np.where(mask[..., None], meas.normals, np.nan).astype(
                np.float32
            )
    if meas.modulation is not None:
        quality["fringe_modulation"] = np.where(mask, meas.modulation, np.nan).astype(np.float32)
    q = {
        "tablet_pixels": int(mask.sum()),
        "tablet_fraction_of_image": float(mask.mean()),
        "coverage": float(_has_normal(meas.normals)[mask].mean())
        if meas.normals is not None
        else float(np.isfinite(meas.fringe_height_um)[mask].mean()),
        "fringe_coverage": float(np.isfinite(meas.fringe_height_um)[mask].mean())
        if meas.fringe_height_um is not None
        else 0.0,
    }
    if "photometric_residual" in quality:
        q["median_residual"] = _median(quality["photometric_residual"], mask)
        q["median_lights_used"] = _median(quality["lights_used"].astype(np.float32), mask)
    if "fringe_modulation" in quality:
        q["median_modulation"] = _median(quality["fringe_modulation"], mask)
    if meas.rgb_srgb8 is not None:  # encoded by the colour stage; sRGB(0) = 0
        albedo8 = np.where(mask[..., None], meas.rgb_srgb8, np.uint8(0))
    else:
        rgb = (
            meas.rgb_linear
            if meas.rgb_linear is not None
            else np.repeat(meas.albedo[..., None], 3, 2)
        )
        albedo8 = linear_to_srgb8(np.where(mask[..., None], rgb, 0))
    return _MaskProducts(quality, q, albedo8, albedo_png_bytes(albedo8))


def _quality_maps(meas: Measurements, height, mask, on_mask: dict) -> dict[str, np.ndarray]:
    """The quality maps: those of the mask alone (`_mask_products`) and the fringes'
    disagreement with the surface."""
    out = dict(on_mask)
    if meas.fringe_height_um is not None:
        out["fringe_disagreement_um"] = np.where(
            mask, meas.fringe_height_um - height, np.nan
        ).astype(np.float32)
    return out


def _median(a, mask):
    """np.median of the finite values of `a` on the mask (by the exact radix select:
    ~25 → 8 ms per map at 1.3 Mpx; the mask products are computed again when the guard
    leaves pixels NaN), None without any."""
    v = a[mask & np.isfinite(a)]
    return float(fast_median(v)) if v.size else None


def _report(meas: Measurements, mask, quality, figures, *, fusion, surface) -> dict:
    q = dict(figures)
    if "fringe_disagreement_um" in quality:
        d = quality["fringe_disagreement_um"]
        q["median_abs_disagreement_um"] = _median(np.abs(d), mask)
    return {
        "format": "digital-hammurabi-model",
        "version": 1,
        "scan": meas.scan_info,
        "pixel_size_um": meas.pixel_size_um,
        "image_size": {"width": int(mask.shape[1]), "height": int(mask.shape[0])},
        "fusion": fusion,
        "surface": surface,
        "used": meas.used,
        "warnings": list(meas.warnings),
        "quality": q,
    }
