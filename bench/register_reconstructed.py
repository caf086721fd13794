"""Registration from real reconstructions: simulate the six faces of a tablet, reconstruct each
with the pipeline, register them, and compare the relative poses with the simulator's truth.

    .venv/bin/python bench/register_reconstructed.py [--size 160x128] [--seed 0] [--work DIR]
        [--rim] [--wrong-pose-sweep]

Unlike bench/register.py (ground-truth heights: the registration alone), this measures the
whole chain that a museum's scans go through. Prints a Markdown table (wall and CPU seconds
per stage, the largest relative rotation and translation error over all pairs of scans, the
same when the registration is given the simulator's true heights on the reconstruction's own
masks and normals, and the median point-to-surface RMS of the overlapping pairs). ``--rim``
adds a table of the reconstructed heights' error against the ground truth by view tilt (the
overlaps between views lie on the steep rims).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "worker" / "register"))

from synthetic import relative_errors, truth_transform  # noqa: E402

from worker.pipeline import reconstruct_bundle  # noqa: E402
from worker.register.io import load_model_dir  # noqa: E402
from worker.register.pointcloud import scan_cloud  # noqa: E402
from worker.register.refine import register_scans  # noqa: E402
from worker.simulate import simulate_scan  # noqa: E402


class _Clock:
    def __init__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def lap(self) -> tuple[float, float]:
        w, c = time.perf_counter(), time.process_time()
        out = (w - self.wall, c - self.cpu)
        self.wall, self.cpu = w, c
        return out


def rim_table(raw: dict, gt_dirs: dict) -> None:
    """Reconstructed − true height (µm) on the pixels registration uses, by view tilt; the
    flat part's median offset removed per face; smoothed = 2-pixel Gaussian of the error
    (the low frequencies a rigid fit cannot average out)."""
    bins = [(0, 20), (20, 30), (30, 40), (40, 50), (50, 60), (60, 70)]
    rows = {b: ([], [], [], []) for b in bins}
    for face, r in raw.items():
        gh = np.load(gt_dirs[face] / "height.npy")
        gn = np.load(gt_dirs[face] / "normals.npy")
        mask = r["mask"]
        keep = ndimage.binary_erosion(mask, iterations=2) & np.isfinite(r["height_um"])
        keep &= np.isfinite(gh)
        err = np.where(keep, r["height_um"] - gh, 0.0)
        err = np.where(keep, err - np.median(err[keep & (gn[..., 2] < -0.95)]), 0.0)
        wt = ndimage.gaussian_filter(keep.astype(float), 2.0)
        low = ndimage.gaussian_filter(err, 2.0) / np.maximum(wt, 1e-9)
        tilt = np.degrees(np.arccos(np.clip(-np.nan_to_num(gn[..., 2], nan=-1.0), -1, 1)))
        edge = ndimage.distance_transform_edt(mask)
        fringe = np.isfinite(r["fringe_disagreement_um"])
        for b in bins:
            sel = keep & (tilt >= b[0]) & (tilt < b[1])
            for acc, v in zip(rows[b], (err, low, edge, fringe), strict=True):
                acc.append(v[sel])
    print()
    print(
        "| view tilt ° | pixels | px from mask edge (median) | with fringe height "
        "| median error µm | RMS µm | RMS smoothed µm |"
    )
    print("|---|---|---|---|---|---|---|")
    for b in bins:
        err, low, edge, fringe = (np.concatenate(a) for a in rows[b])
        if not len(err):
            continue
        print(
            f"| {b[0]}–{b[1]} | {len(err)} | {np.median(edge):.0f} | {fringe.mean():.0%} "
            f"| {np.median(err):+.1f} | {np.sqrt(np.mean(err**2)):.1f} "
            f"| {np.sqrt(np.mean(low**2)):.1f} |"
        )


SWEEP_AXES = ([1.0, 1.0, 0.0], [0.0, 1.0, 1.0], [1.0, 0.0, -1.0])


def wrong_pose_sweep(scans: list, truths: list, faces: list[str], angle_deg: float = 20.0) -> None:
    """Each scan's recorded pose in turn turned by `angle_deg` about each of three axes (issue 8:
    robust to a pose 20° wrong); one registration per case, errors against the truth."""
    print()
    print("| turned scan | axis | max rel. rotation ° | max rel. translation µm | wall s (CPU) |")
    print("|---|---|---|---|---|")
    worst, clock = 0.0, _Clock()
    for axis in SWEEP_AXES:
        turn = Rotation.from_rotvec(np.radians(angle_deg) * np.array(axis) / np.linalg.norm(axis))
        for k, face in enumerate(faces):
            bad = list(scans)
            bad[k] = dataclasses.replace(scans[k], pose=turn.as_matrix() @ scans[k].pose)
            rot, trans = relative_errors(register_scans(bad).transforms, truths)
            lap = clock.lap()
            worst = max(worst, rot)
            print(
                f"| {face} | ({axis[0]:g}, {axis[1]:g}, {axis[2]:g}) | {rot:.3f} "
                f"| {trans * 1000:.1f} | {lap[0]:.1f} ({lap[1]:.1f}) |"
            )
    print(f"\nworst rotation over {len(SWEEP_AXES) * len(faces)} cases: {worst:.3f}°")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="160x128")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--work", help="working folder (default: a temporary one); an earlier run's is reused"
    )
    parser.add_argument("--rim", action="store_true", help="also the rim height-error table")
    parser.add_argument(
        "--wrong-pose-sweep",
        action="store_true",
        help="also register with each scan's pose turned 20° about three axes (18 cases)",
    )
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    work = Path(args.work or tempfile.mkdtemp(prefix="register-chain-"))

    clock = _Clock()
    if (work / "sim" / "poses.json").exists():  # --work of an earlier run: reuse its scans
        faces = json.loads((work / "sim" / "poses.json").read_text())["poses"]
        bundles = {f: work / "sim" / f / "bundle" for f in faces}
        gt_dirs = {f: work / "sim" / f / "gt" for f in faces}
    else:
        sim = simulate_scan(work / "sim", seed=args.seed, face="all", preset="quick", size=size)
        bundles, gt_dirs = sim.bundles, sim.gt_dirs
    t_sim = clock.lap()
    poses = json.loads((work / "sim" / "poses.json").read_text())["poses"]

    scans, truths, raw = [], [], {}
    for face, bundle in bundles.items():
        model_dir = work / "models" / face
        if not (model_dir / "report.json").exists():
            reconstruct_bundle(bundle, model_dir)
        report = json.loads((model_dir / "report.json").read_text())
        scan, arrays = load_model_dir(model_dir)
        scans.append(scan)
        raw[face] = arrays | {
            "normals": np.load(model_dir / "normals.npy"),
            "fringe_disagreement_um": np.load(model_dir / "quality" / "fringe_disagreement_um.npy"),
        }
        pose = poses[face]
        truths.append(truth_transform(np.array(pose["rotation"]), np.array(pose["translation_um"])))
    t_rec = clock.lap()

    registration = register_scans(scans)
    t_reg = clock.lap()
    rotation_deg, translation_mm = relative_errors(registration.transforms, truths)
    surface = [p.surface_rms_um for p in registration.pairs if p.surface_rms_um is not None]

    # The same registration on the true heights, with the reconstruction's masks and normals:
    # what the registration reaches when the heights at the rims are right.
    true_height = [
        scan_cloud(
            np.load(gt_dirs[face] / "height.npy"),
            raw[face]["normals"],
            raw[face]["mask"],
            raw[face]["albedo"],
            pixel_size_um=s.pixel_size_um,
            label=s.label,
            face=s.face,
            pose=s.pose,
        )
        for face, s in zip(raw, scans, strict=True)
    ]
    rot_true, trans_true = relative_errors(register_scans(true_height).transforms, truths)

    print(
        "| views | size | pixel µm | simulate s (CPU) | reconstruct s (CPU) | register s (CPU) "
        "| max rel. rotation ° | max rel. translation µm | same, true heights ° / µm "
        "| pair surface RMS µm (median) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {len(scans)} | {args.size} | {report['pixel_size_um']:.1f} "
        f"| {t_sim[0]:.1f} ({t_sim[1]:.1f}) | {t_rec[0]:.1f} ({t_rec[1]:.1f}) "
        f"| {t_reg[0]:.1f} ({t_reg[1]:.1f}) | {rotation_deg:.3f} | {translation_mm * 1000:.1f} "
        f"| {rot_true:.3f} / {trans_true * 1000:.1f} | {np.median(surface):.1f} |"
    )
    if args.rim:
        rim_table(raw, gt_dirs)
    if args.wrong_pose_sweep:
        wrong_pose_sweep(scans, truths, list(raw))


if __name__ == "__main__":
    main()
