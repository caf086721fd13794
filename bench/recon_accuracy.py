"""Accuracy of reconstruction stages 1–5 on a simulated bundle against its ground truth.

Simulates one face with ``worker.simulate`` (quick preset, default noise unless told), runs
the measurement stages exactly as the pipeline does (``worker.measure.measure_bundle``:
flat field → photometric stereo → colour; fringe phase → unwrapping → heights → combination
over azimuths), and prints error statistics of each product over the tablet mask.

    .venv/bin/python bench/recon_accuracy.py [--size 160x128] [--seed 3] [--preset quick]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from worker.bundle import open_bundle
from worker.measure import measure_bundle
from worker.recon.height import fill_holes
from worker.simulate.scan import simulate_scan


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
            meas = measure_bundle(bundle, progress=lambda stage, fraction: None)
        t_rec = time.perf_counter() - t0
    err_deg = np.degrees(np.arccos(np.clip(np.sum(meas.normals * gt["normals"], -1), -1, 1)))
    e_h = np.abs(meas.fringe_height_um - gt["height"])
    filled = fill_holes(meas.fringe_height_um, mask)
    e_rgb = np.abs(meas.rgb_linear - gt["albedo"])
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
