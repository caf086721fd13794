"""Scans of the simulator's synthetic tablet straight from its ground truth (no frames are
rendered or reconstructed): what registration sees from a perfect reconstruction."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from worker.register.pointcloud import scan_cloud
from worker.simulate.acquisition import pixel_size_for
from worker.simulate.tablet import FACE_POSES, make_tablet
from worker.simulate.view import render_view


def oblique_poses(n: int) -> dict[str, np.ndarray]:
    """Views turned by 60° steps about the tablet's x and y axes (the paper's ~10 scans)."""
    out = {}
    steps = [("x", a) for a in (60, 120, 240, 300)] + [("y", a) for a in (60, 120, 240, 300)]
    for axis, a in steps[:n]:
        out[f"{axis}{a}"] = Rotation.from_euler(axis, a, degrees=True).as_matrix()
    return out


def truth_transform(pose: np.ndarray, translation_um: np.ndarray) -> np.ndarray:
    """Scan → tablet (mm) from the simulator's X_view = pose·X + t (µm)."""
    t = np.eye(4)
    t[:3, :3] = pose.T
    t[:3, 3] = -pose.T @ np.asarray(translation_um) / 1000.0
    return t


def simulated_scans(*, seed: int = 0, size=(160, 128), n_oblique: int = 0, supersample: int = 2):
    """(tablet, [ScanCloud with the true pose], [true 4×4 scan → tablet transforms], pixel µm)."""
    tablet = make_tablet(seed)
    w, h = size
    pixel = pixel_size_for(w, h)
    poses = {**{f: FACE_POSES[f] for f in FACE_POSES}, **oblique_poses(n_oblique)}
    scans, truths = [], []
    for label, pose in poses.items():
        view = render_view(
            tablet, pose, width=w, height=h, pixel_size_um=pixel, supersample=supersample
        )
        gt = view.ground_truth()
        albedo8 = np.rint(255 * np.clip(np.nan_to_num(gt["albedo"]), 0, 1) ** (1 / 2.2)).astype(
            np.uint8
        )
        face = label if label in FACE_POSES else "other"
        scans.append(
            scan_cloud(
                gt["height"],
                gt["normals"],
                gt["mask"],
                albedo8,
                pixel_size_um=pixel,
                label=label,
                face=face,
                pose=pose,
            )
        )
        truths.append(truth_transform(view.pose, view.translation_um))
    return tablet, scans, truths, pixel


def relative_errors(est: list[np.ndarray], truth: list[np.ndarray]):
    """Max over scan pairs of the relative rotation error (deg) and of the displacement (mm)
    the relative error causes at the scan's points' typical radius (20 mm): both frame-free."""
    rot, trans = 0.0, 0.0
    for i in range(len(est)):
        for j in range(len(est)):
            if i == j:
                continue
            e = np.linalg.inv(est[j]) @ est[i]
            t = np.linalg.inv(truth[j]) @ truth[i]
            d = np.linalg.inv(t) @ e
            ang = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
            rot = max(rot, float(ang))
            trans = max(trans, float(np.linalg.norm(d[:3, 3])))
    return rot, trans


def write_gt_model_dirs(out, *, seed: int = 0, size=(96, 80), faces=None, pose_of=None):
    """Model directories (height.npy, normals.npy, mask.png, albedo.png, report.json) made
    from the simulator's ground truth of each face; ``pose_of(face)`` overrides the recorded
    pose (None: no pose). Returns (paths, true scan → tablet transforms)."""
    import json
    from pathlib import Path

    from PIL import Image

    tablet = make_tablet(seed)
    w, h = size
    pixel = pixel_size_for(w, h)
    paths, truths = [], []
    for face in faces or list(FACE_POSES):
        view = render_view(
            tablet, FACE_POSES[face], width=w, height=h, pixel_size_um=pixel, supersample=2
        )
        gt = view.ground_truth()
        d = Path(out) / face
        d.mkdir(parents=True)
        np.save(d / "height.npy", gt["height"])
        np.save(d / "normals.npy", gt["normals"])
        Image.fromarray((gt["mask"] * 255).astype(np.uint8)).save(d / "mask.png")
        albedo8 = np.rint(255 * np.clip(np.nan_to_num(gt["albedo"]), 0, 1) ** (1 / 2.2)).astype(
            np.uint8
        )
        Image.fromarray(albedo8).save(d / "albedo.png")
        pose = FACE_POSES[face] if pose_of is None else pose_of(face)
        report = {
            "scan": {
                "id": f"sim-{seed}-{face}",
                "face": face,
                "pose": None if pose is None else np.asarray(pose).tolist(),
            },
            "pixel_size_um": pixel,
            "image_size": {"width": w, "height": h},
        }
        (d / "report.json").write_text(json.dumps(report))
        paths.append(d)
        truths.append(truth_transform(view.pose, view.translation_um))
    return paths, truths
