"""Does the trust map's σ_h (worker/trust.py) cover the true height error?

Simulates scans with ``worker.simulate`` (quick preset), reconstructs them with the pipeline
(``worker.pipeline.reconstruct_bundle``), derives the trust assets as the worker does, and
compares |h − h_true| with σ_h over the tablet mask, per source class: the share of pixels
whose error is within σ_h and within 2σ_h (a Gaussian error with that σ: 68 % and 95 %), the
median σ_h and the median error. Heights are compared after removing their median offset
(a photometric-only surface has no absolute height).

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/trust_calibration.py \
        [--size 320x256] [--seeds 1,2] [--noise default,hard] [--physics ideal,random]
"""

from __future__ import annotations

import argparse
import io
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from worker.pipeline import reconstruct_bundle
from worker.simulate.scan import simulate_scan
from worker.trust import TRUST_CLASSES
from worker.trust_assets import trust_assets

SHORT = {1: "agree", 2: "disagree", 3: "normals only", 4: "filled", 5: "refined"}


def one(out: Path, *, seed: int, size, noise: str, physics: str) -> list[str]:
    simulate_scan(out / "sim", seed=seed, size=size, preset="quick", noise=noise, physics=physics)
    reconstruct_bundle(out / "sim" / "bundle", out / "model")
    model = out / "model"
    h = np.load(model / "height.npy")
    report = json.loads((model / "report.json").read_text())
    assets = trust_assets(model, h, report)
    sigma = np.load(io.BytesIO(assets["uncertainty_um.npy"]))
    rgba = cv2.imdecode(np.frombuffer(assets["trust.png"], np.uint8), cv2.IMREAD_UNCHANGED)
    classes = rgba[..., 2]  # BGRA: red is last but one
    truth = np.load(out / "sim" / "gt" / "height.npy")
    ok = np.isfinite(h) & np.isfinite(truth) & np.isfinite(sigma)
    err = h - truth
    err -= np.median(err[ok])
    rows = []
    for code in [0, *TRUST_CLASSES]:
        sel = ok if code == 0 else ok & (classes == code)
        n = int(sel.sum())
        if n == 0:
            continue
        e = np.abs(err[sel])
        s = sigma[sel]
        rows.append(
            f"| {seed} | {noise} | {physics} | {'all' if code == 0 else SHORT[code]} | "
            f"{n / ok.sum():.3f} | {np.median(s):.2f} | {np.median(e):.2f} | "
            f"{(e <= s).mean():.2f} | {(e <= 2 * s).mean():.2f} |"
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--noise", default="default,hard")
    ap.add_argument("--physics", default="ideal,random")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    print(
        "| seed | noise | physics | class | share | median σ_h (µm) | median |error| (µm) "
        "| within σ_h | within 2σ_h |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    for seed in (int(s) for s in args.seeds.split(",")):
        for noise in args.noise.split(","):
            for physics in args.physics.split(","):
                with tempfile.TemporaryDirectory() as tmp:
                    for row in one(Path(tmp), seed=seed, size=size, noise=noise, physics=physics):
                        print(row, flush=True)
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
