"""Where the height error at chip cliffs comes from, and what the fringe mixture fit does.

    .venv/bin/python bench/cliffs.py --scan /work/cache/paper-default-s1 [--top 20]
                                     [--point-truth]

On a simulated scan (OUT/bundle + OUT/gt of worker.simulate): measures the bundle, fuses
(default fusion, sharpened by the measured camera blur, as `bench/reconstruct.py`), then
refines the cliff pixels (`pipeline.refine_walls` = `recon.walls.refine_cliff_heights`)
and prints, over the evaluated pixels of `worker.recon.evaluate` (tablet ≥ 4 px from the
gt mask edge, gt slope < 60°, median offset removed):
1. height RMS before / after, and two oracles on the same sides: every refined pixel on
   its better side (what a side choice alone can reach), and the true area fraction with
   the estimated sides (what is left to the side heights);
2. the share of the squared error by distance to a true jump between neighbours
   > 2 px·s, before / after;
3. the worst pixels before: truth, fused height, fringe height, the two sides, the fitted
   upper-side fraction f and the new height;
4. with --point-truth: the scene re-rendered with one sample at each pixel centre (the
   point that the spec's frame says the pixel images); RMS against that truth of the
   area-mean output and of a point output (the side the centre lies on: upper iff f > ½).
The ground truth of the simulator is each pixel's area mean (2×2 sub-samples), which is
what a real pixel integrates; the point figure is the other reading of the spec.
"""

from __future__ import annotations

import sys
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from worker.bundle import open_bundle  # noqa: E402
from worker.measure import measure_bundle  # noqa: E402
from worker.pipeline import _mask, camera_blur_px, surface_of  # noqa: E402
from worker.recon.walls import refine_cliff_heights  # noqa: E402


def evaluated(gt_h, gt_n, gt_mask, mask, h) -> np.ndarray:
    """The pixels `worker.recon.evaluate` scores."""
    inner = ndimage.binary_erosion(gt_mask, np.ones((3, 3), bool), iterations=4)
    inner &= np.abs(gt_n[..., 2]) > np.cos(np.radians(60.0))
    return inner & mask & np.isfinite(h)


def errors(h, truth, sel) -> np.ndarray:
    """Height error map (0 off ``sel``), the median offset over ``sel`` removed."""
    e = np.where(sel, h - truth, 0.0)
    return np.where(sel, e - np.median(e[sel]), 0.0)


def rms(e, sel) -> float:
    return float(np.sqrt(np.mean(e[sel] ** 2)))


def jump_distance(gt_h, s) -> np.ndarray:
    """Distance (px) to the nearest pixel with a 4-neighbour more than 2 px·s away in gt."""
    g = np.nan_to_num(gt_h, nan=-1e6)
    j = np.zeros(g.shape, bool)
    dx = np.abs(np.diff(g, axis=1)) > 2 * s
    dy = np.abs(np.diff(g, axis=0)) > 2 * s
    j[:, 1:] |= dx
    j[:, :-1] |= dx
    j[1:] |= dy
    j[:-1] |= dy
    return ndimage.distance_transform_edt(~j)


def point_truth(scan: Path, shape) -> np.ndarray:
    """gt heights sampled once at each pixel centre (re-rendered from the manifest's seed)."""
    from worker.simulate.acquisition import pixel_size_for
    from worker.simulate.tablet import make_tablet
    from worker.simulate.view import render_view

    man = json.loads((scan / "bundle" / "manifest.json").read_text())
    seed = int(man["scan"]["id"].split("-")[1])  # "sim-{seed}-{face}-{size}-{noise}"
    rows, cols = shape
    view = render_view(
        make_tablet(seed),
        np.asarray(man["scan"]["pose"], float),
        width=cols,
        height=rows,
        pixel_size_um=pixel_size_for(cols, rows),
        supersample=1,
    )
    return np.where(view.tablet_ss, view.height_ss_um, np.nan).astype(np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scan", required=True, help="simulated scan folder (bundle/ and gt/)")
    p.add_argument("--top", type=int, default=20)
    p.add_argument("--point-truth", action="store_true")
    args = p.parse_args(argv)
    scan = Path(args.scan)
    missing = [str(scan / n) for n in ("bundle", "gt/height.npy") if not (scan / n).exists()]
    if missing:
        p.error(f"--scan {scan}: not a simulated scan folder (missing {', '.join(missing)})")
    gt = {k: np.load(scan / "gt" / f"{k}.npy") for k in ("height", "normals", "mask")}
    with open_bundle(scan / "bundle") as b:
        meas = measure_bundle(b, progress=lambda s, f: None)
        blur = camera_blur_px(b)
    mask = _mask(meas)
    s = meas.pixel_size_um
    h0, _, _ = surface_of(meas, mask, fusion="default", surface="fused", blur_sigma_px=blur)
    c0 = time.process_time()
    ref = refine_cliff_heights(
        h0,
        meas.fringe_height_um,
        meas.normals,
        mask,
        meas.cliff_samples,
        pixel_size_um=s,
        blur_sigma_px=blur,
    )
    cpu = time.process_time() - c0
    h1 = np.where(mask, ref.height_um, h0)
    kept = sum(
        c.amplitude.nbytes + c.phase_rad.nbytes + c.flat_index.nbytes for c in meas.cliff_samples
    )
    truth = gt["height"]
    sel = evaluated(truth, gt["normals"], gt["mask"], mask, h0)
    e0, e1 = errors(h0, truth, sel), errors(h1, truth, sel)
    done = np.isfinite(ref.fraction)
    hi, lo, f = ref.upper_um, ref.lower_um, ref.fraction
    better = np.where(np.abs(hi - truth) < np.abs(lo - truth), hi, lo)
    h_side = np.where(done, better, h1)
    with np.errstate(invalid="ignore", divide="ignore"):
        f_true = np.clip((truth - lo) / (hi - lo), 0, 1)
    h_ftrue = np.where(done, f_true * hi + (1 - f_true) * lo, h1)
    print(f"scan {scan}, camera blur σ = {blur:.3f} px, pixel {s:.1f} µm")
    print(
        f"samples kept: {len(meas.cliff_samples)} azimuths, "
        f"{[c.flat_index.size for c in meas.cliff_samples]} pixels, {kept / 2**20:.0f} MiB; "
        f"refined {int(done.sum())} pixels ({int((done & sel).sum())} evaluated) in {cpu:.2f} CPU s"
    )
    print("\n| surface | height RMS µm |\n|---|---|")
    print(f"| default fusion (now) | {rms(e0, sel):.2f} |")
    print(f"| + cliff refinement (area mean f·h_hi + (1 − f)·h_lo) | {rms(e1, sel):.2f} |")
    print(
        f"| oracle: refined pixels on their better side | {rms(errors(h_side, truth, sel), sel):.2f} |"
    )
    print(
        f"| oracle: true fraction, estimated sides | {rms(errors(h_ftrue, truth, sel), sel):.2f} |"
    )

    dist = jump_distance(truth, s)
    print(
        "\n| distance to a true jump (px) | pixels | share of e² before | RMS before µm | "
        "share after | RMS after µm |\n|---|---|---|---|---|---|"
    )
    t0, t1 = np.sum(e0[sel] ** 2), np.sum(e1[sel] ** 2)
    for a, b in ((0, 0.5), (0.5, 1.5), (1.5, 2.5), (2.5, 4), (4, np.inf)):
        m = sel & (dist >= a) & (dist < b)
        if m.any():
            print(
                f"| [{a}, {b}) | {int(m.sum())} | {np.sum(e0[m] ** 2) / t0:.3f} | {rms(e0, m):.1f} "
                f"| {np.sum(e1[m] ** 2) / t1:.3f} | {rms(e1, m):.1f} |"
            )

    print(f"\nWorst {args.top} pixels before (µm; f = fitted upper-side area fraction):\n")
    print("| row | col | truth | fused | fringe | upper | lower | f | f true | new | error after |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rr, cc = np.nonzero(sel)
    for k in np.argsort(-np.abs(e0[rr, cc]))[: args.top]:
        r, c = rr[k], cc[k]
        print(
            f"| {r} | {c} | {truth[r, c]:.0f} | {h0[r, c]:.0f} | {meas.fringe_height_um[r, c]:.0f} "
            f"| {hi[r, c]:.0f} | {lo[r, c]:.0f} | {f[r, c]:.2f} | {f_true[r, c]:.2f} "
            f"| {h1[r, c]:.0f} | {e1[r, c]:+.0f} |"
        )
    if args.point_truth:
        pt = point_truth(scan, truth.shape)
        sel_p = sel & np.isfinite(pt)
        h_pt = np.where(done, np.where(f > 0.5, hi, lo), h1)
        print("\nAgainst the point truth (height at each pixel centre, re-rendered):\n")
        print("| surface | height RMS µm |\n|---|---|")
        print(f"| the area-mean ground truth itself | {rms(errors(truth, pt, sel_p), sel_p):.2f} |")
        print(f"| default fusion (now) | {rms(errors(h0, pt, sel_p), sel_p):.2f} |")
        print(f"| + cliff refinement, area mean | {rms(errors(h1, pt, sel_p), sel_p):.2f} |")
        print(
            f"| + cliff refinement, point (upper iff f > ½) | {rms(errors(h_pt, pt, sel_p), sel_p):.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
