"""Accuracy of reconstruction stages 1–5 on a simulated bundle against its ground truth.

Simulates one face with ``worker.simulate`` (quick preset, default noise unless told), runs
flat field → photometric stereo → colour, and 4-step → temporal unwrapping → heights →
combination over azimuths, and prints error statistics over the tablet mask.

    .venv/bin/python bench/recon_accuracy.py [--size 160x128] [--seed 3] [--preset quick]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from worker.bundle import open_bundle
from worker.recon.color import rgb_reflectance
from worker.recon.fringe import four_step_phase
from worker.recon.height import combine_azimuths, fill_holes, height_from_phase
from worker.recon.photometric import light_directions, photometric_stereo
from worker.recon.radiometry import flat_field
from worker.recon.unwrap import phase_difference, temporal_unwrap
from worker.simulate.scan import simulate_scan


def _shading(bundle, frames, rho_ref):
    refs = [bundle.reference_of(f) for f in frames]
    polar = [f.polar_deg for f in frames]
    s = flat_field(
        bundle.radiance_many(frames),
        bundle.radiance_many(refs),
        reference_reflectance=rho_ref,
        polar_deg=polar,
    )
    return s, light_directions([f.azimuth_deg for f in frames], polar)


def _heights(bundle):
    fringe = [f for f in bundle.frames if f.kind == "fringe" and f.target == "object"]
    heights, weights = [], []
    for az in sorted({f.azimuth_deg for f in fringe}):
        periods = sorted({f.period_um for f in fringe if f.azimuth_deg == az}, reverse=True)
        diffs, mods = [], []
        for p in periods:
            fs = sorted(
                [f for f in fringe if f.azimuth_deg == az and f.period_um == p],
                key=lambda f: f.phase_deg,
            )
            o = four_step_phase(bundle.radiance_many(fs))
            r = four_step_phase(bundle.radiance_many([bundle.reference_of(f) for f in fs]))
            diffs.append(phase_difference(o.phase_rad, r.phase_rad))
            mods.append(np.minimum(o.modulation, r.modulation))
        un = temporal_unwrap(np.stack(diffs), periods, modulation=np.stack(mods))
        heights.append(
            height_from_phase(un.dpsi_rad, period_um=periods[-1], polar_deg=fs[0].polar_deg)
        )
        weights.append(np.where(un.order_residual < 0.25, un.weight, 0.0))
    return combine_azimuths(np.stack(heights), np.stack(weights))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="160x128")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--noise", default="default")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        t0 = time.perf_counter()
        simulate_scan(out, seed=args.seed, size=(w, h), preset=args.preset, noise=args.noise)
        t_sim = time.perf_counter() - t0
        gt = {k: np.load(out / "gt" / f"{k}.npy") for k in ("normals", "height", "albedo", "mask")}
        mask = gt["mask"]
        t0 = time.perf_counter()
        with open_bundle(out / "bundle") as bundle:
            rho_ref = bundle.manifest.reference.reflectance
            photo = [f for f in bundle.frames if f.kind == "photometric" and f.target == "object"]
            s, lights = _shading(bundle, photo, rho_ref)
            ps = photometric_stereo(s, lights)
            col = [f for f in bundle.frames if f.kind == "color" and f.target == "object"]
            cs, clights = _shading(bundle, col, rho_ref)
            rgb = rgb_reflectance(cs, [f.channel for f in col], clights, ps.normals).rgb
            comb = _heights(bundle)
        t_rec = time.perf_counter() - t0
    err_deg = np.degrees(np.arccos(np.clip(np.sum(ps.normals * gt["normals"], -1), -1, 1)))
    e_h = np.abs(comb.height_um - gt["height"])
    filled = fill_holes(comb.height_um, mask)
    e_rgb = np.abs(rgb - gt["albedo"])
    m = mask

    def q(x):
        x = x[np.isfinite(x)]
        return f"{np.median(x):9.3f} {np.percentile(x, 90):9.3f} {np.percentile(x, 99):9.3f}"

    print(
        f"simulated {args.preset} {w}x{h} seed {args.seed} noise {args.noise}: "
        f"simulation {t_sim:.1f} s, stages 1-5 incl. decoding {t_rec:.1f} s (wall)"
    )
    print(
        f"{'quantity over the tablet mask':36s} {'median':>9s} {'p90':>9s} {'p99':>9s} {'cover':>6s}"
    )
    print(f"{'normal error (deg)':36s} {q(err_deg[m])} {np.isfinite(err_deg[m]).mean():6.3f}")
    print(f"{'fringe height error (um)':36s} {q(e_h[m])} {np.isfinite(e_h[m]).mean():6.3f}")
    print(
        f"{'height error after fill_holes (um)':36s} {q(np.abs(filled - gt['height'])[m])} "
        f"{np.isfinite(filled[m]).mean():6.3f}"
    )
    for i, name in enumerate(("red", "green", "blue")):
        print(
            f"{'reflectance error ' + name:36s} {q(e_rgb[..., i][m])} "
            f"{np.isfinite(e_rgb[..., i][m]).mean():6.3f}"
        )


if __name__ == "__main__":
    main()
