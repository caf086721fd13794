"""Benchmark of worker.register on the simulator: a tablet seen from six faces plus oblique
views (60° steps about the tablet's x and y axes), from the simulator's ground-truth heights
(a perfect reconstruction), registered from the recorded poses.

    .venv/bin/python bench/register.py [--size 160x128] [--oblique 4] [--dpi 300]

Prints a Markdown table: views, image size, pixel size, wall (CPU) seconds per stage, the largest
relative rotation (°) and translation (µm) error over all pairs of scans, and the RMS
distance (µm) of the merged surface to the ground-truth mesh.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "worker" / "register"))

from synthetic import relative_errors, simulated_scans  # noqa: E402

from worker.register.fatcross import FATCROSS_VIEWS, natural_colour, render_orthographic  # noqa: E402
from worker.register.merge import merged_surface  # noqa: E402
from worker.register.o3d import o3d, transform_points  # noqa: E402
from worker.register.refine import register_scans  # noqa: E402
from worker.simulate.mesh import tablet_mesh  # noqa: E402


def surface_rms_um(merged, est, truths, tablet) -> float:
    """RMS distance of the merged vertices to the true mesh, after mapping the estimated
    tablet frame onto the true one through the first scan (est and truth agree on it)."""
    to_true = truths[0] @ np.linalg.inv(est[0])
    v = transform_points(to_true, merged.vertices)
    gt = tablet_mesh(tablet, resolution=192)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(gt.vertices.astype(np.float32)), o3d.core.Tensor(gt.faces.astype(np.uint32))
    )
    d = scene.compute_distance(o3d.core.Tensor(v.astype(np.float32))).numpy()
    return float(np.sqrt(np.mean(d.astype(np.float64) ** 2)) * 1000.0)


class _Laps:
    """Wall and CPU seconds since the last call, as "wall (CPU)"."""

    def __init__(self):
        self.t = (time.perf_counter(), time.process_time())

    def __call__(self) -> str:
        now = (time.perf_counter(), time.process_time())
        wall, cpu = now[0] - self.t[0], now[1] - self.t[1]
        self.t = now
        return f"{wall:.1f} ({cpu:.1f})"


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--size", default="160x128")
    p.add_argument("--oblique", type=int, default=4)
    p.add_argument("--dpi", type=float, default=300.0)
    args = p.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    lap = _Laps()
    tablet, scans, truths, pixel = simulated_scans(size=size, n_oblique=args.oblique)
    t_sim = lap()
    reg = register_scans(scans)
    t_reg = lap()
    merged = merged_surface(scans, reg.transforms)
    t_merge = lap()
    for rot in FATCROSS_VIEWS.values():
        natural_colour(
            render_orthographic(
                merged.vertices,
                merged.faces,
                merged.visual.vertex_colors,
                merged.vertex_normals,
                rot,
                px_per_mm=args.dpi / 25.4,
            )
        )
    t_plates = lap()
    rot, trans = relative_errors(reg.transforms, truths)
    rms = surface_rms_um(merged, reg.transforms, truths, tablet)
    print(
        "| views | size | pixel µm | simulate s (CPU) | register s (CPU) | merge s (CPU) "
        "| plates s (CPU) | max rel. rotation ° | max rel. translation µm | merged RMS µm |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {len(scans)} | {args.size} | {pixel:.1f} | {t_sim} | {t_reg} | {t_merge} | "
        f"{t_plates} | {rot:.3f} | {trans * 1000:.1f} | {rms:.1f} |"
    )


if __name__ == "__main__":
    main()
