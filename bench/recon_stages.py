"""Speed and memory of reconstruction stages 1–5 at the paper's image size.

Synthetic arrays from the spec formulas (no I/O): 1280×1024 pixels, 16 photometric
azimuths, 12 colour frames, 4 fringe azimuths × 10 periods × 4 phases on object and
reference (320 fringe frames).  Prints one row per stage: wall and CPU seconds, and the
peak traced numpy memory of the stage (tracemalloc).

    .venv/bin/python bench/recon_stages.py [--size 1280x1024]
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from worker.recon.color import linear_to_srgb8, rgb_reflectance
from worker.recon.fringe import carre_phase, four_step_phase, intensity_noise, phase_sigma_rad
from worker.recon.height import consensus_azimuths, fill_holes, height_from_phase
from worker.recon.photometric import light_directions, photometric_stereo
from worker.recon.radiometry import flat_field
from worker.recon.unwrap import noise_aware_unwrap

ROWS: list[tuple[str, float, float, float]] = []


def timed(name, fn, *args, **kwargs):
    tracemalloc.start()
    t, c = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    ROWS.append((name, wall, cpu, peak))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="1280x1024")
    w, h = (int(v) for v in ap.parse_args().size.split("x"))
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    height = 800 * np.sin(xx / 97) * np.cos(yy / 131)
    gx, gy = np.gradient(height, 26.8)
    n = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    rho = rng.uniform(0.3, 0.7, (h, w)).astype(np.float32)

    az = np.arange(16) * 22.5
    lights = light_directions(az, 45.0)
    cos = np.einsum("hwc,kc->khw", n, lights).astype(np.float32)
    obj = (0.8 * rho * np.clip(cos, 0, None) + rng.normal(0, 0.003, cos.shape)).astype(np.float32)
    ref = np.full(obj.shape, 0.8 * np.cos(np.pi / 4), dtype=np.float32)
    s = timed(
        "flat_field (16 frames)", flat_field, obj, ref, reference_reflectance=1.0, polar_deg=45.0
    )
    ps = timed("photometric_stereo (K=16)", photometric_stereo, s, lights)

    col_az = np.repeat([45.0, 135.0, 225.0, 315.0], 3)
    col_lights = light_directions(col_az, 45.0)
    ch = ["red", "green", "blue"] * 4
    ccos = np.einsum("hwc,kc->khw", n, col_lights).astype(np.float32)
    cs = (rho * np.clip(ccos, 0, None)).astype(np.float32)
    rgb = timed("rgb_reflectance (12 frames)", rgb_reflectance, cs, ch, col_lights, ps.normals)
    timed("linear_to_srgb8", linear_to_srgb8, rgb.rgb)

    periods = 34304.0 / (0.25 * 2.0 ** np.arange(10))
    heights, sigmas = [], []
    phase_rows = {
        "four_step_phase (80 sets)": [0.0, 0.0],
        "phase noise (80 sets, obj + ref)": [0.0, 0.0],
        "carre_phase (80 sets)": [0.0, 0.0],
    }
    for a in (0.0, 90.0, 180.0, 270.0):
        diffs, noise = [], []
        for p in periods:
            psi_ref = (2 * np.pi * xx / (p / 26.8)).astype(np.float32)
            dpsi = (-2 * np.pi * height / p).astype(np.float32)
            fo = np.stack(
                [
                    0.4 * (1 + 0.85 * np.cos(psi_ref + dpsi + d))
                    + rng.normal(0, 0.003, psi_ref.shape)
                    for d in np.deg2rad([0, 90, 180, 270])
                ]
            )
            fr = np.stack(
                [
                    0.5 * (1 + 0.85 * np.cos(psi_ref + d)) + rng.normal(0, 0.003, psi_ref.shape)
                    for d in np.deg2rad([0, 90, 180, 270])
                ]
            )
            t, c = time.perf_counter(), time.process_time()
            o, r = four_step_phase(fo), four_step_phase(fr)
            row = phase_rows["four_step_phase (80 sets)"]
            row[0] += time.perf_counter() - t
            row[1] += time.process_time() - c
            # The phase noise as the pipeline estimates it (worker.measure.fringe).
            t, c = time.perf_counter(), time.process_time()
            sig_o = phase_sigma_rad(o, intensity_noise(o.mean, o.residual, phase_rad=o.phase_rad))
            sig_r = phase_sigma_rad(r, intensity_noise(r.mean, r.residual, phase_rad=r.phase_rad))
            noise.append(np.sqrt(sig_o**2 + sig_r**2))
            row = phase_rows["phase noise (80 sets, obj + ref)"]
            row[0] += time.perf_counter() - t
            row[1] += time.process_time() - c
            t, c = time.perf_counter(), time.process_time()
            carre_phase(fo)
            carre_phase(fr)
            row = phase_rows["carre_phase (80 sets)"]
            row[0] += time.perf_counter() - t
            row[1] += time.process_time() - c
            diffs.append(o.phase_rad - r.phase_rad)
        un = timed(
            f"noise_aware_unwrap (az {a:.0f}, 10 levels)",
            noise_aware_unwrap,
            np.stack(diffs),
            np.stack(noise),
            periods,
        )
        heights.append(height_from_phase(un.dpsi_rad, period_um=periods[-1], polar_deg=45.0))
        sigmas.append(
            np.abs(height_from_phase(un.sigma_rad, period_um=periods[-1], polar_deg=45.0))
        )
    for name, (wall, cpu) in phase_rows.items():
        ROWS.append((name, wall, cpu, float("nan")))
    comb = timed(
        "consensus_azimuths (A=4)", consensus_azimuths, np.stack(heights), np.stack(sigmas)
    )
    holes = comb.height_um.copy()
    holes[rng.uniform(size=holes.shape) < 0.01] = np.nan
    timed("fill_holes (1 % holes)", fill_holes, holes, np.ones(holes.shape, dtype=bool))

    print(
        f"size {w}x{h}; height error of combined fringe heights (µm): "
        f"median {np.nanmedian(np.abs(comb.height_um - height)):.3f}"
    )
    print(f"{'stage':40s} {'wall s':>8s} {'cpu s':>8s} {'peak MiB':>9s}")
    for name, wall, cpu, peak in ROWS:
        print(f"{name:40s} {wall:8.3f} {cpu:8.3f} {peak:9.1f}")


if __name__ == "__main__":
    main()
