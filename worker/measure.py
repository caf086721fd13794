"""Measurement stages 1–5 driven from a bundle: photometric normals, colour, fringe heights.

Streams the frames: each group (the photometric frames, the colour frames, one fringe set
of four phases with its reference set) is decoded in threads while the previous group is
processed, in float32, and dropped once reduced. Calls the pure functions of `worker.recon`.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from worker.recon.color import rgb_reflectance
from worker.recon.fringe import four_step_phase
from worker.recon.height import combine_azimuths, height_from_phase
from worker.recon.photometric import PhotometricResult, light_directions, photometric_stereo
from worker.recon.radiometry import flat_field
from worker.recon.unwrap import phase_difference, temporal_unwrap

__all__ = ["Measurements", "ReconstructionError", "measure_bundle"]

HIGHLIGHT_CONE_DEG = 20.0


class ReconstructionError(Exception):
    """The bundle cannot be reconstructed; the message names the culprit."""


@dataclass
class Measurements:
    """Per-pixel products of stages 1–5, all (H, W[, 3]) float32 in the spec frame."""

    pixel_size_um: float
    shape: tuple[int, int]
    normals: np.ndarray | None = None
    albedo: np.ndarray | None = None  # grey ρ relative to white (photometric, else fringes)
    residual: np.ndarray | None = None
    lights_used: np.ndarray | None = None
    photometric_polar_deg: float = 45.0
    rgb_linear: np.ndarray | None = None
    fringe_height_um: np.ndarray | None = None
    fringe_spread_um: np.ndarray | None = None
    azimuths_used: np.ndarray | None = None
    modulation: np.ndarray | None = None
    rough_height_um: np.ndarray | None = None  # smooth, filled: where the light came from
    used: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    scan_info: dict = field(default_factory=dict)


def _prefetch(bundle, groups: Sequence[Sequence], workers: int = 2) -> Iterator[np.ndarray]:
    """Radiance stacks of the groups, decoding group i+1 while the caller works on group i."""
    if not groups:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        future = pool.submit(bundle.radiance_many, groups[0], max_workers=workers)
        for i in range(len(groups)):
            stack = future.result()
            if i + 1 < len(groups):
                future = pool.submit(bundle.radiance_many, groups[i + 1], max_workers=workers)
            yield stack


def _key(angle: float) -> float:
    return round(float(angle) % 360.0, 6)


def measure_bundle(bundle, *, progress: Callable[[str, float], None]) -> Measurements:
    """Run stages 1–5 on an open `worker.bundle.Bundle`."""
    man = bundle.manifest
    cam = man.camera
    meas = Measurements(pixel_size_um=float(cam.pixel_size_um), shape=(cam.height, cam.width))
    meas.scan_info = {
        "id": man.scan.id,
        "face": man.scan.face,
        # scan.pose initialises the registration of a tablet's scans (worker.register).
        "pose": None if man.scan.pose is None else [list(map(float, r)) for r in man.scan.pose],
    }
    obj = [f for f in bundle.frames if f.target == "object"]
    counts: dict[str, int] = defaultdict(int)
    for f in bundle.frames:
        counts[f.kind if f.target == "object" else f"reference_{f.kind}"] += 1
    meas.used["frames"] = dict(counts)
    rho_ref = float(man.reference.reflectance)

    t0 = time.perf_counter()
    progress("fringe", 0.02)
    fringe = [f for f in obj if f.kind == "fringe"]
    if fringe:
        _fringes(bundle, fringe, meas, rho_ref, progress)
    meas.timings["fringe"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress("photometric", 0.55)
    photo = [f for f in obj if f.kind == "photometric"]
    if len(photo) >= 3:
        _photometric(bundle, photo, meas, rho_ref)
    elif photo:
        meas.warnings.append(
            f"photometric: {len(photo)} object frame(s), at least 3 are needed; normals not computed"
        )
    meas.timings["photometric"] = time.perf_counter() - t0

    if meas.normals is None and meas.fringe_height_um is None:
        raise ReconstructionError(
            "bundle: nothing to reconstruct (needs ≥ 3 photometric object frames or fringe sets "
            "with reference frames); frames found: "
            + (", ".join(f"{k}={v}" for k, v in sorted(counts.items())) or "none")
        )

    t0 = time.perf_counter()
    progress("color", 0.75)
    color = [f for f in obj if f.kind == "color"]
    if color:
        _color(bundle, color, meas, rho_ref)
    meas.timings["color"] = time.perf_counter() - t0
    return meas


def _source_footprint(ref_stack, frames, height_um, pixel_size_um):
    """Reference radiance at p′ = p − h·tanθ·u instead of p (in place).

    The light that reaches the surface point above p crossed the reference plane at p′
    (SCAN_BUNDLE.md): with a non-uniform source the flat field must be read there, or the
    shading of each light is off by E(p′)/E(p), a few per cent per millimetre of height,
    which tilts the normals by about a degree.
    """
    rows, cols = height_um.shape
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float32)
    for k, f in enumerate(frames):
        shift = height_um * np.float32(np.tan(np.radians(f.polar_deg)) / pixel_size_um)
        phi = np.radians(f.azimuth_deg)
        map_x = c - shift * np.float32(np.sin(phi))
        map_y = r - shift * np.float32(np.cos(phi))
        ref_stack[k] = cv2.remap(
            ref_stack[k],
            map_x,
            map_y,
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return ref_stack


def _shading(bundle, frames, stack, rho_ref, meas, kind):
    refs = [bundle.reference_of(f) for f in frames]
    polar = np.array([f.polar_deg for f in frames], np.float64)
    if all(r is not None for r in refs):
        ref_stack = bundle.radiance_many(refs)
        if meas.rough_height_um is not None:
            ref_stack = _source_footprint(
                ref_stack, frames, meas.rough_height_um, meas.pixel_size_um
            )
        return flat_field(stack, ref_stack, reference_reflectance=rho_ref, polar_deg=polar)
    meas.warnings.append(
        f"{kind}: no reference frames; assuming uniform illumination, albedo is relative"
    )
    # Without a flat field: s = L·cosθ / (bright level of the brightest frame), one scale for
    # all frames so that their ratios (which carry the normals) are kept.
    scale = float(np.nanpercentile(stack, 99.5)) or 1.0
    return (stack * (np.cos(np.radians(polar))[:, None, None] / scale)).astype(np.float32)


def _photometric(bundle, photo, meas, rho_ref):
    stack = bundle.radiance_many(photo)
    shading = _shading(bundle, photo, stack, rho_ref, meas, "photometric")
    del stack
    az = np.array([f.azimuth_deg for f in photo])
    polar = np.array([f.polar_deg for f in photo])
    lights = light_directions(az, polar)
    res = _without_highlights(shading, lights, photometric_stereo(shading, lights))
    meas.normals = res.normals
    meas.albedo = res.albedo
    meas.residual = res.residual
    meas.lights_used = res.lights_used
    meas.photometric_polar_deg = float(np.median(polar))
    meas.used["photometric_azimuths_deg"] = sorted({_key(a) for a in az})


def _without_highlights(shading, lights, first, *, cone_deg=HIGHLIGHT_CONE_DEG, min_left=4):
    """Solve again, without the samples seen near the mirror direction of their light.

    A glossy surface (fired clay, consolidants) adds a highlight where the normal is near
    the half vector h_k = (l_k + v)/|l_k + v| of light k and the camera direction v =
    (0, 0, −1). Highlights a few per cent above the Lambertian shading pass any outlier test
    yet tilt the normal by a degree or more; the geometry tells where they can be, so those
    samples are dropped (NaN) when at least `min_left` lights remain, and the pixels solved
    again. The cone (20°) is where a Blinn–Phong lobe of exponent ≥ 40 still exceeds 1 % of
    its peak.
    """
    half = lights + np.array([0.0, 0.0, -1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    n = first.normals
    cos = np.einsum("hwc,kc->khw", np.nan_to_num(n), half.astype(np.float32))
    near = cos > np.float32(np.cos(np.radians(cone_deg)))
    left = np.sum(np.isfinite(shading) & ~near, axis=0)
    redo = near.any(axis=0) & (left >= min_left) & np.all(np.isfinite(n), axis=-1)
    if not redo.any():
        return first
    cleaned = np.where(near & redo[None], np.float32(np.nan), shading)
    second = photometric_stereo(cleaned, lights, mask=redo)
    ok = redo & np.all(np.isfinite(second.normals), axis=-1)
    return PhotometricResult(
        normals=np.where(ok[..., None], second.normals, first.normals),
        albedo=np.where(ok, second.albedo, first.albedo),
        residual=np.where(ok, second.residual, first.residual),
        lights_used=np.where(ok, second.lights_used, first.lights_used),
    )


def _color(bundle, color, meas, rho_ref):
    if meas.normals is None:
        meas.warnings.append("color: frames ignored (no normals to divide the shading by)")
        return
    stack = bundle.radiance_many(color)
    shading = _shading(bundle, color, stack, rho_ref, meas, "color")
    del stack
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
    meas.used["color_azimuths_deg"] = sorted({_key(a) for a in az})
    meas.used["color_channels"] = sorted({f.channel for f in color})


def _fringe_sets(bundle, fringe, meas):
    """{(azimuth, polar): [(period, [4 object frames], [4 reference frames]), coarse → fine]}."""
    sets: dict = defaultdict(lambda: defaultdict(list))
    for f in fringe:
        sets[(_key(f.azimuth_deg), round(f.polar_deg, 6))][round(f.period_um, 6)].append(f)
    out = {}
    for key, by_period in sorted(sets.items()):
        levels = []
        for period, frames in sorted(by_period.items(), reverse=True):
            frames = sorted(frames, key=lambda f: _key(f.phase_deg))
            phases = [_key(f.phase_deg) for f in frames]
            refs = [bundle.reference_of(f) for f in frames]
            if phases != [0.0, 90.0, 180.0, 270.0]:
                meas.warnings.append(
                    f"fringe: azimuth {key[0]}°, period {period} µm: phases {phases} "
                    "are not 0/90/180/270; set ignored"
                )
                continue
            if any(r is None for r in refs):
                meas.warnings.append(
                    f"fringe: azimuth {key[0]}°, period {period} µm has no reference frames; "
                    "set ignored (the reference phase is needed for heights)"
                )
                continue
            levels.append((period, frames, refs))
        if levels:
            out[key] = levels
    return out


def _fringes(bundle, fringe, meas, rho_ref, progress):
    sets = _fringe_sets(bundle, fringe, meas)
    if not sets:
        meas.warnings.append("fringe: no usable fringe set; heights not computed")
        return
    groups, index = [], []
    for key, levels in sets.items():
        for level, (_, frames, refs) in enumerate(levels):
            groups.append([*frames, *refs])
            index.append((key, level))
    heights, weights, mods, ambient = [], [], [], []
    wrapped: dict = defaultdict(list)
    finest_mod: dict = {}
    total = len(groups)
    for i, stack in enumerate(_prefetch(bundle, groups)):
        key, level = index[i]
        obj_phase = four_step_phase(stack[:4])
        ref_phase = four_step_phase(stack[4:])
        wrapped[key].append(phase_difference(obj_phase.phase_rad, ref_phase.phase_rad))
        levels = sets[key]
        if level == len(levels) - 1:
            finest_mod[key] = obj_phase.modulation
            with np.errstate(invalid="ignore", divide="ignore"):
                # Mean level A of the object relative to the reference: ρ·max(0, n·l)/cosθ.
                a_obj = stack[:4].mean(axis=0)
                a_ref = stack[4:].mean(axis=0)
                ambient.append(
                    np.where(a_ref > 0, a_obj / a_ref * rho_ref, np.nan).astype(np.float32)
                )
            dpsi = np.stack(wrapped.pop(key))
            periods = np.array([p for p, _, _ in levels])
            un = temporal_unwrap(dpsi, periods)
            h = height_from_phase(un.dpsi_rad, period_um=float(periods[-1]), polar_deg=key[1])
            m = finest_mod.pop(key)
            ok = np.isfinite(h) & (m > 0.1) & (un.order_residual < 0.25)
            heights.append(np.where(ok, h, np.nan).astype(np.float32))
            weights.append(np.where(ok, np.square(np.nan_to_num(m)), 0).astype(np.float32))
            mods.append(np.where(np.isfinite(m), m, np.nan).astype(np.float32))
        progress("fringe", 0.02 + 0.5 * (i + 1) / total)
    comb = combine_azimuths(np.stack(heights), np.stack(weights))
    meas.fringe_height_um = comb.height_um
    meas.fringe_spread_um = comb.spread_um
    meas.azimuths_used = comb.azimuths_used
    with np.errstate(invalid="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            meas.modulation = np.nanmax(np.stack(mods), axis=0).astype(np.float32)
            if meas.albedo is None:
                meas.albedo = np.nanmax(np.stack(ambient), axis=0).astype(np.float32)
    meas.rough_height_um = _rough_height(comb.height_um)
    meas.used["fringe_azimuths_deg"] = sorted({k[0] for k in sets})
    meas.used["fringe_periods_um"] = {
        f"{k[0]:g}": [float(p) for p, _, _ in levels] for k, levels in sets.items()
    }
    meas.used["fringe_sets"] = sum(len(v) for v in sets.values())


def _rough_height(height_um):
    """Fringe heights made whole and smooth (5×5 median, nearest fill, Gaussian σ = 2 px)."""
    finite = np.isfinite(height_um)
    if not finite.any():
        return None
    idx = ndimage.distance_transform_edt(~finite, return_distances=False, return_indices=True)
    filled = height_um[tuple(idx)]
    return ndimage.gaussian_filter(ndimage.median_filter(filled, size=5), 2.0).astype(np.float32)
