"""Stages 4–5 from a bundle: fringe phase, temporal unwrapping, heights per azimuth, combined."""

from __future__ import annotations

import warnings
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import cv2
import numpy as np
from scipy import ndimage

from worker.measure.checks import check_reference_periods, measured_period_px
from worker.measure.frames import angle_key, prefetch
from worker.recon.arrays import copy_where, fast_median
from worker.recon.fringe import four_step_phase, intensity_noise, phase_sigma_rad
from worker.recon.height import consensus_azimuths, height_from_phase
from worker.recon.unwrap import noise_aware_unwrap
from worker.recon.walls import cliff_samples

__all__ = ["fringe_sets", "measure_fringes"]

_Z = float(np.sqrt(2.0 * np.log(1e3)))  # noise_aware_unwrap's default max_ambiguity 1e-3


def fringe_sets(bundle, fringe, warnings: list[str]) -> dict:
    """{(azimuth, polar): [(period, [4 object frames], [4 reference frames]), coarse → fine]}.

    Sets whose phases are not the standard 0/90/180/270° or that lack reference frames are
    left out, each with a line in `warnings`."""
    sets: dict = defaultdict(lambda: defaultdict(list))
    for f in fringe:
        sets[(angle_key(f.azimuth_deg), round(f.polar_deg, 6))][round(f.period_um, 6)].append(f)
    out = {}
    for key, by_period in sorted(sets.items()):
        levels = []
        for period, frames in sorted(by_period.items(), reverse=True):
            frames = sorted(frames, key=lambda f: angle_key(f.phase_deg))
            phases = [angle_key(f.phase_deg) for f in frames]
            refs = [bundle.reference_of(f) for f in frames]
            if phases != [0.0, 90.0, 180.0, 270.0]:
                warnings.append(
                    f"fringe: azimuth {key[0]}°, period {period} µm: phases {phases} "
                    "are not 0/90/180/270; set ignored"
                )
                continue
            if any(r is None for r in refs):
                warnings.append(
                    f"fringe: azimuth {key[0]}°, period {period} µm has no reference frames; "
                    "set ignored (the reference phase is needed for heights)"
                )
                continue
            levels.append((period, frames, refs))
        if levels:
            out[key] = levels
    return out


def measure_fringes(bundle, fringe, meas, rho_ref, progress, *, workers: int = 1, on_queued=None):
    """Fringe heights into `meas`; on_queued() is called once every fringe frame is queued
    for decoding (the caller may then start decoding other frames)."""
    # What the stages after this one do not wait for runs beside it (the last azimuth's
    # cliff samples, the maxima over azimuths beside the consensus and the rough heights).
    with ThreadPoolExecutor(max_workers=1) as side:
        _measure_fringes(bundle, fringe, meas, rho_ref, progress, workers, side, on_queued)


def _measure_fringes(bundle, fringe, meas, rho_ref, progress, workers, side, on_queued):
    sets = fringe_sets(bundle, fringe, meas.warnings)
    if not sets:
        meas.warnings.append("fringe: no usable fringe set; heights not computed")
        return
    groups, index = [], []
    for key, levels in sets.items():
        for level, (_, frames, refs) in enumerate(levels):
            groups.append([*frames, *refs])
            index.append((key, level))
    heights, sigmas, mods, ambient = [], [], [], []
    summary: dict = {}
    harmonic_sets = 0
    wrapped: dict = {}
    noise: dict = {}
    amps: dict = defaultdict(list)  # per level (object B, reference B), for cliff_samples
    total = len(groups)
    blur_key = next(iter(sets))
    periods_seen: list = []  # (azimuth, nominal, measured period px) of blur_key's references
    cliff_jobs = []
    # One decoding thread more than cores: a thread blocked on a read or the GIL leaves no
    # core idle (fringe stage 5.4–5.9 → 4.8–5.3 s at 1.3 Mpx on 2 cores, three groups ahead).
    # Six groups ahead: the decoding goes on while an azimuth is unwrapped (with three the
    # threads ran out of groups there and the cores idled; +130 MB).
    # Nothing below keeps a view of a stack past its iteration: buffers are reused.
    ahead = 6
    stacks = prefetch(bundle, groups, workers=workers + 1, ahead=ahead, reuse=True)
    # The arrays of a group's results are written over by the next group's (fresh arrays
    # cost their page faults, as much as the arithmetic): all but the amplitudes, which
    # cliff_samples takes at the end of the azimuth, and the σ stack once unwrapped.
    obj_phase = ref_phase = None
    sig = sig_ref = noise_buffer = None
    nan_frame = None  # NaN source of the masked copies below (np.where branches per pixel)
    for i, stack in enumerate(stacks):
        if on_queued is not None and i == max(0, total - 1 - ahead):
            on_queued()  # the prefetch has queued the frames of every group
        key, level = index[i]
        # Modulation is kept for the finest object set and the camera blur's reference sets.
        last = level == len(sets[key]) - 1
        obj_phase = four_step_phase(stack[:4], modulation=last, out=_reusable(obj_phase))
        ref_phase = four_step_phase(stack[4:], modulation=key == blur_key, out=_reusable(ref_phase))
        amps[key].append((obj_phase.amplitude, ref_phase.amplitude))
        period_px = sets[key][level][0] / meas.pixel_size_um
        if key == blur_key and 3 <= period_px <= min(meas.shape) / 2:
            periods_seen.append((key[0], period_px, measured_period_px(ref_phase.phase_rad)))
        if level == 0:
            shape = (len(sets[key]), *obj_phase.phase_rad.shape)
            wrapped[key] = np.empty(shape, np.float32)
            if noise_buffer is None or noise_buffer.shape != shape:
                noise_buffer = np.empty(shape, np.float32)
            noise[key] = noise_buffer
        # Object − reference, left in (−2π, 2π): noise_aware_unwrap wraps where it matters.
        np.subtract(obj_phase.phase_rad, ref_phase.phase_rad, out=wrapped[key][level])
        obj_noise, ref_noise = _noise(obj_phase), _noise(ref_phase)
        harmonic_sets += obj_noise.harmonic != (0.0, 0.0) or ref_noise.harmonic != (0.0, 0.0)
        sig = phase_sigma_rad(obj_phase, obj_noise, out=sig)
        sig_ref = phase_sigma_rad(ref_phase, ref_noise, out=sig_ref)
        # Object and reference noise are independent: variances add in the difference.
        sig *= sig
        sig_ref *= sig_ref
        sig += sig_ref
        np.sqrt(sig, out=noise[key][level])
        levels = sets[key]
        if level == len(levels) - 1:
            if nan_frame is None:
                nan_frame = np.full(obj_phase.mean.shape, np.nan, np.float32)
            with np.errstate(invalid="ignore", divide="ignore"):
                # Mean level A of the object relative to the reference: ρ·max(0, n·l)/cosθ.
                level_ratio = np.divide(obj_phase.mean, ref_phase.mean)
                level_ratio *= np.float32(rho_ref)
            copy_where(level_ratio, nan_frame, ~(ref_phase.mean > 0))
            ambient.append(level_ratio)
            periods = np.array([p for p, _, _ in levels])
            wrapped_az = wrapped.pop(key)
            un = noise_aware_unwrap(
                wrapped_az, noise.pop(key), periods, workers=workers, diagnostics=False
            )
            h = height_from_phase(un.dpsi_rad, period_um=float(periods[-1]), polar_deg=key[1])
            sigma_h = np.abs(
                height_from_phase(un.sigma_rad, period_um=float(periods[-1]), polar_deg=key[1])
            )
            # One level rejected although its fringe was seen is common (a corrupt level, a
            # blurred finest period); two or more mostly mean an order went wrong before.
            # A pixel that stopped at a coarse level may be right but is too imprecise to
            # be a measurement (σ_h up to mm, worse than filling from its neighbours): keep
            # it only if its phase could fix the finest period's order (σ ≤ π/z, z of the
            # unwrapping's ambiguity test).
            ok = np.isfinite(h) & (un.conflicts <= 1) & (un.sigma_rad * _Z <= np.pi)
            summary[f"{key[0]:g}"] = _unwrap_summary(un, ok, periods)
            rejected = ~ok
            copy_where(h, nan_frame, rejected)
            heights.append(h)
            b_obj, b_ref = zip(*amps.pop(key), strict=True)
            cliff_jobs.append(
                side.submit(
                    cliff_samples,
                    heights[-1],
                    wrapped_az,
                    list(b_obj),
                    list(b_ref),
                    period_um=periods,
                    polar_deg=key[1],
                    pixel_size_um=meas.pixel_size_um,
                )
            )
            copy_where(sigma_h, nan_frame, rejected)
            sigmas.append(sigma_h)
            m = obj_phase.modulation.copy()  # its buffer is the next set's
            copy_where(m, nan_frame, ~np.isfinite(m))
            mods.append(m)
        if key == blur_key:
            # Reported (the projector's and camera's modulation transfer), not used.
            period = sets[key][level][0]
            meas.reference_modulation[(*key, period)] = _central_median(ref_phase.modulation)
        progress("fringe", 0.02 + 0.5 * (i + 1) / total)
    check_reference_periods(periods_seen)
    maxima = side.submit(_maxima, mods, ambient if meas.albedo is None else None)
    meas.fringe_azimuth_heights_um = np.stack(heights)
    meas.fringe_azimuth_sigma_um = np.stack(sigmas)
    comb = consensus_azimuths(
        meas.fringe_azimuth_heights_um, meas.fringe_azimuth_sigma_um, workers=workers
    )
    meas.fringe_height_um = comb.height_um
    meas.fringe_spread_um = comb.spread_um
    meas.fringe_sigma_um = comb.sigma_um
    meas.azimuths_used = comb.azimuths_used
    meas.rough_height_um = _rough_height(comb.height_um)
    meas.cliff_samples.extend(job.result() for job in cliff_jobs)
    meas.modulation, albedo = maxima.result()
    if albedo is not None:
        meas.albedo = albedo
    meas.used["fringe_azimuths_deg"] = sorted({k[0] for k in sets})
    meas.used["fringe_periods_um"] = {
        f"{k[0]:g}": [float(p) for p, _, _ in levels] for k, levels in sets.items()
    }
    meas.used["fringe_sets"] = sum(len(v) for v in sets.values())
    meas.used["fringe_unwrap"] = {"azimuths": summary, "sets_with_harmonic": int(harmonic_sets)}


def _maxima(mods, ambient):
    """Per pixel, the largest modulation and mean level over the azimuths (NaN-aware)."""
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        modulation = np.nanmax(np.stack(mods), axis=0).astype(np.float32)
        albedo = None if ambient is None else np.nanmax(np.stack(ambient), axis=0)
    return modulation, None if albedo is None else albedo.astype(np.float32)


def _unwrap_summary(un, ok, periods) -> dict:
    """What the unwrapping of one azimuth did, for the report (fractions of the pixels whose
    coarsest fringe was seen, i.e. lit at that azimuth)."""
    lit = un.level_used >= 0
    n = max(np.count_nonzero(lit), 1)
    lev = un.level_used[ok]
    return {
        "kept": round(np.count_nonzero(ok) / n, 4),
        "conflicts": round(np.count_nonzero(lit & (un.conflicts > 1)) / n, 4),
        "finest_period_um_median": float(periods[_median_level(lev)]) if lev.size else None,
    }


def _median_level(levels) -> int:
    """int(np.median(levels)) of level indices (≥ 0) from their counts: the middle one, or
    the mean of the two middle ones truncated (np.median sorts a megapixel's worth)."""
    below = np.cumsum(np.bincount(levels))  # how many are ≤ each level

    def ranked(k: int) -> int:  # the level of rank k in ascending order
        return int(np.searchsorted(below, k, side="right"))

    n = levels.size
    if n % 2:
        return ranked(n // 2)
    return int((ranked(n // 2 - 1) + ranked(n // 2)) / 2)


def _central_median(a) -> float:
    """Median of the finite values of the central half of the frame (away from its border)."""
    rows, cols = a.shape
    m = a[rows // 4 : rows - rows // 4, cols // 4 : cols - cols // 4]
    m = m[np.isfinite(m)]
    return float(fast_median(m)) if m.size else float("nan")


def _reusable(phase):
    """The arrays of a previous set's result that the next one may write over: not its
    amplitude, kept for cliff_samples."""
    return None if phase is None else replace(phase, amplitude=None)


def _noise(phase):
    return intensity_noise(phase.mean, phase.residual, phase_rad=phase.phase_rad)


def _rough_height(height_um):
    """Fringe heights made whole and smooth (5×5 median, nearest fill, Gaussian σ = 2 px)."""
    finite = np.isfinite(height_um)
    if not finite.any():
        return None
    rows, cols = ndimage.distance_transform_edt(
        ~finite, return_distances=False, return_indices=True
    )
    # Gathered by flat indices: height_um[rows, cols] took 2.5× as long (5.5 → 2.1 ms).
    nearest = rows.astype(np.intp)
    nearest *= height_um.shape[1]
    nearest += cols
    filled = np.take(height_um, nearest)
    return ndimage.gaussian_filter(_median5(filled), 2.0).astype(np.float32)


def _median5(a):
    """5×5 median, borders mirrored about the edge as by ``ndimage.median_filter`` (its
    'reflect'): OpenCV's float median picks the same values some 40× faster."""
    padded = np.pad(np.asarray(a, np.float32), 2, mode="symmetric")
    return cv2.medianBlur(padded, 5)[2:-2, 2:-2]
