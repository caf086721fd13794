"""Registration from real reconstructions: simulate the six faces of a tablet, reconstruct each
with the pipeline, register them, and compare the relative poses with the simulator's truth.

    .venv/bin/python bench/register_reconstructed.py [--size 160x128] [--seed 0] [--work DIR]

Unlike bench/register.py (ground-truth heights: the registration alone), this measures the
whole chain that a museum's scans go through. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "worker" / "register"))

from synthetic import relative_errors, truth_transform  # noqa: E402

from worker.pipeline import reconstruct_bundle  # noqa: E402
from worker.register.io import load_model_dir  # noqa: E402
from worker.register.refine import register_scans  # noqa: E402
from worker.simulate import simulate_scan  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="160x128")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", help="working folder (default: a temporary one)")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    work = Path(args.work or tempfile.mkdtemp(prefix="register-chain-"))

    t0 = time.perf_counter()
    sim = simulate_scan(work / "sim", seed=args.seed, face="all", preset="quick", size=size)
    t_sim = time.perf_counter() - t0
    poses = json.loads((work / "sim" / "poses.json").read_text())["poses"]

    scans, truths = [], []
    t0 = time.perf_counter()
    for face, bundle in sim.bundles.items():
        model_dir = work / "models" / face
        report = reconstruct_bundle(bundle, model_dir)
        scans.append(load_model_dir(model_dir)[0])
        pose = poses[face]
        truths.append(truth_transform(np.array(pose["rotation"]), np.array(pose["translation_um"])))
    t_rec = time.perf_counter() - t0

    t0 = time.perf_counter()
    registration = register_scans(scans)
    t_reg = time.perf_counter() - t0
    rotation_deg, translation_mm = relative_errors(registration.transforms, truths)

    print(
        "| views | size | pixel µm | simulate s | reconstruct s | register s "
        "| max rel. rotation ° | max rel. translation µm |"
    )
    print("|---|---|---|---|---|---|---|---|")
    print(
        f"| {len(scans)} | {args.size} | {report['pixel_size_um']:.1f} | {t_sim:.1f} | "
        f"{t_rec:.1f} | {t_reg:.1f} | {rotation_deg:.3f} | {translation_mm * 1000:.1f} |"
    )


if __name__ == "__main__":
    main()
