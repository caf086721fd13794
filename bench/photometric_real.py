"""Photometric stereo on photograph-like bundles: objects rendered by Mitsuba 3 (our second
instrument) on a dark ground under 96 DiLiGenT-like lights, photometric frames only (no
projector, no reference target), reconstructed through the real CLI.

The real benchmark, DiLiGenT (Shi et al. 2019: best non-learning mean angular errors about
1.3° on "ball", 5° on "cat", 12° on "harvest"), cannot be fetched here (no network); these
renders stand in for it: a matte ball, a dark glossy ball, a cat-like figurine of spheres
with concave creases (cast shadows, interreflections, mild gloss) and a shiny heap of
spheres full of interreflections (`worker.simulate.mitsuba.objects`).

    .venv/bin/python bench/photometric_real.py [--work DIR] [--size 128] [--spp 16] [names...]

Renders are cached in --work (delete a folder to render it again). For each object and
each chain (`--fusion plain`: least squares over the lit samples; the default), prints the
mean and median angular error (degrees) over the true object pixels that the chain
reconstructed, of the written normals (normals.npy, the surface's) and of the measured
photometric normals (quality/photometric_normals.npy, the default's only), the share of
true object pixels covered, and the mask IoU against the true silhouette; then, per
object, the measured normals of both chains over the true object pixels that both
reconstructed (the estimators compared on the same pixels, rim pixels that only one mask
keeps left out).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from worker.simulate.mitsuba.objects import OBJECTS, render_object_bundle  # noqa: E402


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between unit normals a and b, (..., 3); NaN where either is NaN."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def evaluate(model_dir: Path, gt_dir: Path) -> dict:
    """Errors of one model directory against the ground truth folder."""
    gt_mask = np.load(gt_dir / "mask.npy")
    gt_n = np.load(gt_dir / "normals.npy")
    mask = cv2.imread(str(model_dir / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    out = {
        "iou": float((mask & gt_mask).sum() / max((mask | gt_mask).sum(), 1)),
    }
    maps = {"surface": np.load(model_dir / "normals.npy")}
    measured = model_dir / "quality" / "photometric_normals.npy"
    if measured.exists():
        maps["measured"] = np.load(measured)
    for key, n in maps.items():
        err = angular_error_deg(n, gt_n)
        have = gt_mask & mask & np.isfinite(err)
        out[f"{key}_coverage"] = float(have.sum() / gt_mask.sum())
        out[f"{key}_mean"] = float(np.mean(err[have])) if have.any() else float("nan")
        out[f"{key}_median"] = float(np.median(err[have])) if have.any() else float("nan")
    return out


def common_errors(scene: Path) -> dict:
    """Measured normals of both chains over the true object pixels both reconstructed."""
    gt_mask = np.load(scene / "gt" / "mask.npy")
    gt_n = np.load(scene / "gt" / "normals.npy")
    err = {}
    common = gt_mask.copy()
    for fusion in ("plain", "default"):
        model = scene / f"model-{fusion}"
        mask = cv2.imread(str(model / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
        err[fusion] = angular_error_deg(
            np.load(model / "quality" / "photometric_normals.npy"), gt_n
        )
        common &= mask & np.isfinite(err[fusion])
    out = {"pixels": int(common.sum())}
    for fusion, e in err.items():
        out[f"{fusion}_mean"] = float(np.mean(e[common]))
        out[f"{fusion}_median"] = float(np.median(e[common]))
    return out


def reconstruct(bundle: Path, out: Path, fusion: str) -> float:
    """Run the CLI; returns its wall time in seconds."""
    t0 = time.perf_counter()
    subprocess.run(
        [
            sys.executable,
            "-m",
            "worker.reconstruct",
            str(bundle),
            str(out),
            "--fusion",
            fusion,
            "--quiet",
        ],
        check=True,
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
    )
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", default=list(OBJECTS))
    parser.add_argument("--work", default="/tmp/photometric_real")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--spp", type=int, default=16)
    args = parser.parse_args(argv)
    work = Path(args.work)
    rows, common_rows = [], []
    for name in args.names:
        scene = work / f"{name}-{args.size}-{args.spp}"
        if not (scene / "gt").exists():
            t0 = time.perf_counter()
            render_object_bundle(scene, name, size=args.size, spp=args.spp)
            print(f"rendered {name} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        for fusion in ("plain", "default"):
            out = scene / f"model-{fusion}"
            wall = reconstruct(scene / "bundle", out, fusion)
            r = evaluate(out, scene / "gt")
            report = json.loads((out / "report.json").read_text())
            r.update(name=name, fusion=fusion, wall_s=wall, warnings=report["warnings"])
            rows.append(r)
        common_rows.append((name, common_errors(scene)))
    head = (
        f"{'object':18s} {'chain':8s} {'IoU':>6s} {'cover':>6s} {'mean°':>7s} {'median°':>8s}"
        f" {'meas.mean°':>11s} {'meas.med°':>10s} {'wall s':>7s}"
    )
    print(head)
    for r in rows:
        print(
            f"{r['name']:18s} {r['fusion']:8s} {r['iou']:6.3f} {r['surface_coverage']:6.3f}"
            f" {r['surface_mean']:7.2f} {r['surface_median']:8.2f}"
            f" {r.get('measured_mean', float('nan')):11.2f}"
            f" {r.get('measured_median', float('nan')):10.2f} {r['wall_s']:7.1f}"
        )
        for w in r["warnings"]:
            if not w.startswith("photometric: no reference frames"):
                print(f"    warning: {w}")
    print()
    print(
        f"{'object':18s} {'pixels':>7s} {'plain mean°':>12s} {'median°':>8s}"
        f" {'default mean°':>14s} {'median°':>8s}"
    )
    for name, c in common_rows:
        print(
            f"{name:18s} {c['pixels']:7d} {c['plain_mean']:12.2f} {c['plain_median']:8.2f}"
            f" {c['default_mean']:14.2f} {c['default_median']:8.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
