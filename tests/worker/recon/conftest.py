"""Synthetic scenes built from the formulas of SCAN_BUNDLE.md, with the `default` noise preset.

Noise preset `default`: 12-bit ADC, full well 20,000 e-, read noise 10 e-, fringe modulation
0.85.  A pixel whose linear radiance is x (fraction of full scale) collects x·20,000 e- with
Poisson statistics plus N(0, 10 e-) read noise, quantised to 4,095 levels, so that

    σ_x² = x / 20,000 + (10 / 20,000)² + (1 / 4,095)² / 12.

Helpers are fixtures returning plain functions so that tests can call them with their own
seeded generators.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

FULL_WELL_E = 20_000.0
READ_NOISE_E = 10.0
BIT_DEPTH = 12
MODULATION = 0.85


@dataclass(frozen=True)
class Scene:
    """A height field with analytic normals on an (H, W) grid; units µm."""

    height_um: np.ndarray
    normals: np.ndarray
    pixel_size_um: float


def sense(radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Linear radiance (fraction of full scale) → noisy, quantised linear radiance."""
    x = np.clip(np.asarray(radiance, dtype=np.float64), 0.0, None)
    electrons = rng.poisson(x * FULL_WELL_E) + rng.normal(0.0, READ_NOISE_E, x.shape)
    full = 2**BIT_DEPTH - 1
    dn = np.clip(np.round(electrons / FULL_WELL_E * full), 0, full)
    return (dn / full).astype(np.float32)


def sigma_of(radiance: np.ndarray) -> np.ndarray:
    """σ of :func:`sense` at linear radiance x (see module docstring)."""
    x = np.clip(np.asarray(radiance, dtype=np.float64), 0.0, None)
    full = 2**BIT_DEPTH - 1
    return np.sqrt(x / FULL_WELL_E + (READ_NOISE_E / FULL_WELL_E) ** 2 + 1.0 / (12 * full**2))


def sphere_scene(size: int = 64, *, radius_px: float = 40.0, pixel_size_um: float = 20.0) -> Scene:
    """A spherical cap centred in the image; outside the cap the plane h = 0.

    h = sqrt(R² − r²) − z0 with the cap cut at 60° slope; analytic normal
    n = (x − cx, y − cy, −sqrt(R² − r²)) / R (so n_z < 0, spec frame).
    """
    r_um = radius_px * pixel_size_um
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    dx = (xx - (size - 1) / 2) * pixel_size_um
    dy = (yy - (size - 1) / 2) * pixel_size_um
    rr2 = dx**2 + dy**2
    cut = (r_um * np.sin(np.deg2rad(60.0))) ** 2
    inside = rr2 <= cut
    zc = np.sqrt(np.clip(r_um**2 - rr2, 0.0, None))
    z0 = r_um * np.cos(np.deg2rad(60.0))
    height = np.where(inside, zc - z0, 0.0)
    normals = np.zeros((size, size, 3))
    normals[..., 2] = -1.0
    normals[inside] = np.stack([dx[inside], dy[inside], -zc[inside]], axis=1) / r_um
    return Scene(height_um=height, normals=normals, pixel_size_um=pixel_size_um)


def lights(azimuth_deg, polar_deg) -> np.ndarray:
    phi = np.deg2rad(np.asarray(azimuth_deg, dtype=np.float64))
    th = np.deg2rad(np.broadcast_to(np.asarray(polar_deg, dtype=np.float64), phi.shape))
    return np.stack([np.sin(th) * np.sin(phi), np.sin(th) * np.cos(phi), -np.cos(th)], axis=1)


@pytest.fixture
def recon_sense():
    return sense


@pytest.fixture
def recon_sigma():
    return sigma_of


@pytest.fixture
def recon_sphere():
    return sphere_scene


@pytest.fixture
def recon_lights():
    return lights


@pytest.fixture
def recon_noise():
    return {
        "full_well_e": FULL_WELL_E,
        "read_noise_e": READ_NOISE_E,
        "bit_depth": BIT_DEPTH,
        "modulation": MODULATION,
    }


@dataclass(frozen=True)
class SimulatedRecon:
    """Stages 1–5 run on a small simulated bundle, with ground truth and noise predictions."""

    mask: np.ndarray
    smooth: np.ndarray  # interior pixels where the true normal field is smooth (< 2° over 3×3)
    gt_normals: np.ndarray
    gt_height_um: np.ndarray
    gt_albedo: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    sigma_normal_rad: np.ndarray  # predicted RMS angular error from the noise model
    rgb: np.ndarray
    height_um: np.ndarray
    sigma_height_um: np.ndarray  # predicted σ of the combined height from the noise model
    azimuths_used: np.ndarray


def _radiance_sigma(radiance: np.ndarray, exposure: float) -> np.ndarray:
    """σ of a bundle radiance: the frame was read at radiance·exposure of full scale."""
    return sigma_of(radiance * exposure) / exposure


def _smooth_interior(mask: np.ndarray, normals: np.ndarray) -> np.ndarray:
    import scipy.ndimage as ndi

    worst = np.zeros(mask.shape)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nb = np.roll(np.roll(normals, dy, 0), dx, 1)
            worst = np.maximum(worst, np.arccos(np.clip((nb * normals).sum(-1), -1, 1)))
    return mask & (worst < np.deg2rad(2.0)) & ndi.binary_erosion(mask, iterations=2)


def _photometric_part(bundle, rho_ref):
    from worker.recon.photometric import light_directions, photometric_stereo
    from worker.recon.radiometry import flat_field

    frames = [f for f in bundle.frames if f.kind == "photometric" and f.target == "object"]
    refs = [bundle.reference_of(f) for f in frames]
    obj, ref = bundle.radiance_many(frames), bundle.radiance_many(refs)
    polar = [f.polar_deg for f in frames]
    s = flat_field(obj, ref, reference_reflectance=rho_ref, polar_deg=polar)
    lights = light_directions([f.azimuth_deg for f in frames], polar)
    res = photometric_stereo(s, lights)
    # σ_s/s from object and reference radiance noise (ratio of two independent readings).
    rel = np.sqrt(
        np.stack(
            [
                _radiance_sigma(o, f.exposure) / np.maximum(o, 1e-6)
                for o, f in zip(obj, frames, strict=True)
            ]
        )
        ** 2
        + np.stack([_radiance_sigma(r, f.exposure) / r for r, f in zip(ref, refs, strict=True)])
        ** 2
    )
    return s, rel * np.abs(s), lights, res


def _predicted_normal_sigma(lights, sig_s, normals, albedo, inl):
    """RMS angular error of unweighted LS over the lights ``inl`` (K, H, W)."""
    w = inl.astype(float)
    a = np.einsum("khw,ki,kj->hwij", w, lights, lights)
    c = np.einsum("khw,khw,ki,kj->hwij", w, sig_s**2, lights, lights)
    ok = inl.sum(0) >= 3
    ainv = np.linalg.inv(np.where(ok[..., None, None], a, np.eye(3)))
    cov = ainv @ c @ ainv
    p = np.eye(3) - normals[..., :, None] * normals[..., None, :]
    var = np.einsum("hwij,hwjk,hwki->hw", p, cov, p) / albedo**2
    return np.where(ok, np.sqrt(var), np.nan)


def _fringe_part(bundle, mask):
    from worker.recon.fringe import four_step_phase
    from worker.recon.height import combine_azimuths, height_from_phase
    from worker.recon.unwrap import phase_difference, temporal_unwrap

    fringe = [f for f in bundle.frames if f.kind == "fringe" and f.target == "object"]
    heights, weights, inv_var = [], [], []
    for az in sorted({f.azimuth_deg for f in fringe}):
        periods = sorted({f.period_um for f in fringe if f.azimuth_deg == az}, reverse=True)
        diffs, mods, sig_psi = [], [], []
        for p in periods:
            fs = sorted(
                [f for f in fringe if f.azimuth_deg == az and f.period_um == p],
                key=lambda f: f.phase_deg,
            )
            rs = [bundle.reference_of(f) for f in fs]
            o_frames, r_frames = bundle.radiance_many(fs), bundle.radiance_many(rs)
            o, r = four_step_phase(o_frames), four_step_phase(r_frames)
            diffs.append(phase_difference(o.phase_rad, r.phase_rad))
            mods.append(np.minimum(o.modulation, r.modulation))
            # 4-step: σ_ψ ≈ σ_I/(√2·B) with σ_I at the mean level; object and reference add.
            amp_o = np.sqrt(2) * np.maximum(o.amplitude, 1e-9)
            amp_r = np.sqrt(2) * np.maximum(r.amplitude, 1e-9)
            s_o = _radiance_sigma(o_frames.mean(0), fs[0].exposure) / amp_o
            s_r = _radiance_sigma(r_frames.mean(0), rs[0].exposure) / amp_r
            sig_psi.append(np.sqrt(s_o**2 + s_r**2))
        un = temporal_unwrap(np.stack(diffs), periods, modulation=np.stack(mods))
        theta = fs[0].polar_deg
        heights.append(height_from_phase(un.dpsi_rad, period_um=periods[-1], polar_deg=theta))
        weights.append(np.where(un.order_residual < 0.25, un.weight, 0.0))
        lev = np.clip(un.level_used, 0, None)
        sig = np.take_along_axis(np.stack(sig_psi), lev[None], 0)[0]
        p_used = np.asarray(periods)[lev]
        sig_h = sig * p_used / (2 * np.pi * np.tan(np.deg2rad(theta)))
        inv_var.append(np.where(weights[-1] > 0, 1.0 / np.maximum(sig_h, 1e-9) ** 2, 0.0))
    comb = combine_azimuths(np.stack(heights), np.stack(weights))
    total = np.sum(inv_var, axis=0)
    return comb, np.where(total > 0, 1.0 / np.sqrt(np.maximum(total, 1e-30)), np.nan)


@pytest.fixture(scope="session")
def simulated_recon(tmp_path_factory) -> SimulatedRecon:
    """Simulate a quick-preset scan (default noise, 160×128) and run stages 1–5 on it."""
    from worker.bundle import open_bundle
    from worker.recon.color import rgb_reflectance
    from worker.recon.photometric import light_directions
    from worker.recon.radiometry import flat_field
    from worker.simulate.scan import simulate_scan

    out = tmp_path_factory.mktemp("recon_sim")
    result = simulate_scan(out, seed=3, size=(160, 128), preset="quick", noise="default")
    gt = {k: np.load(out / "gt" / f"{k}.npy") for k in ("height", "albedo", "mask")}
    # Photometric stereo measures each pixel's mean normal; gt/normals.npy is the normal at the
    # pixel centre (SCAN_BUNDLE.md), which carries relief finer than a pixel. The noise tests
    # here compare against the pixel mean.
    gt["normals"] = result.views["obverse"].ground_truth()["normals"]
    mask = gt["mask"]
    with open_bundle(out / "bundle") as bundle:
        rho_ref = bundle.manifest.reference.reflectance
        s, sig_s, lights, ps = _photometric_part(bundle, rho_ref)
        inl = (np.einsum("hwc,kc->khw", gt["normals"], lights) > 0.1) & (s > 0.02)
        sig_n = _predicted_normal_sigma(lights, sig_s, gt["normals"], ps.albedo, inl)
        col = [f for f in bundle.frames if f.kind == "color" and f.target == "object"]
        cobj = bundle.radiance_many(col)
        cref = bundle.radiance_many([bundle.reference_of(f) for f in col])
        polar = [f.polar_deg for f in col]
        cs = flat_field(cobj, cref, reference_reflectance=rho_ref, polar_deg=polar)
        clights = light_directions([f.azimuth_deg for f in col], polar)
        rgb = rgb_reflectance(cs, [f.channel for f in col], clights, ps.normals)
        comb, sig_h = _fringe_part(bundle, mask)
    return SimulatedRecon(
        mask=mask,
        smooth=_smooth_interior(mask, gt["normals"]),
        gt_normals=gt["normals"],
        gt_height_um=gt["height"],
        gt_albedo=gt["albedo"],
        normals=ps.normals,
        albedo=ps.albedo,
        sigma_normal_rad=sig_n,
        rgb=rgb.rgb,
        height_um=comb.height_um,
        sigma_height_um=sig_h,
        azimuths_used=comb.azimuths_used,
    )
