"""Registration through the whole chain (issue 8): the six faces of the synthetic tablet are
simulated (quick preset at 160×128, 214 µm pixels, default noise), reconstructed by the
pipeline and registered from their recorded poses.

At this pixel size the issue's 0.05° is *not* reached from the reconstructed heights (measured
0.09–0.24° for seeds 0 and 1; it is at 107 µm pixels, bench/register_reconstructed.py,
docs/registration.md "Accuracy"): the views overlap only on the tablet's steep, rounded rims,
where the reconstructed heights carry smooth errors of a few µm (2–7 µm RMS at 30–60° of
tilt), and a narrow edge scan's roll about its long axis is fixed by those rims alone. What is
tested:

- at 107 µm pixels (320×256) the reconstructed faces meet the issue's 0.05° and one pixel;
- the registration itself meets the issue's criteria on the reconstruction's own masks,
  normals and sampling when the heights are right (the simulator's true heights);
- from the reconstructed heights, the relative poses are within one pixel everywhere on the
  tablet (translation, and rotation times the tablet's radius), also with an edge scan's
  recorded pose 20° wrong (one of the 18 cases of docs/registration.md's sweep).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from worker.pipeline import reconstruct_bundle
from worker.register.align import object_diameter_mm
from worker.register.io import load_model_dir
from worker.register.pointcloud import scan_cloud
from worker.register.refine import register_scans
from worker.simulate import simulate_scan

from .synthetic import relative_errors, truth_transform

SIZE = (160, 128)


def _chain(work, size=SIZE):
    sim = simulate_scan(work / "sim", seed=0, face="all", preset="quick", size=size)
    poses = json.loads((work / "sim" / "poses.json").read_text())["poses"]
    scans, raw, truths = [], [], []
    for face, bundle in sim.bundles.items():
        reconstruct_bundle(bundle, work / face)
        scan, arrays = load_model_dir(work / face)
        scans.append(scan)
        raw.append(
            arrays | {"normals": np.load(work / face / "normals.npy"), "gt": sim.gt_dirs[face]}
        )
        p = poses[face]
        truths.append(truth_transform(np.array(p["rotation"]), np.array(p["translation_um"])))
    return scans, raw, truths


@pytest.mark.slow
def test_six_reconstructed_faces_register(tmp_path):
    """One test (one simulation and six reconstructions, ~20 CPU s) rather than two that
    xdist could give a fixture each."""
    scans, raw, truths = _chain(tmp_path)
    pixel_mm = scans[0].pixel_size_um / 1000

    # 1. The registration itself, on the reconstruction's masks, normals and sampling with
    # the true heights: issue 8's 0.05° and one pixel (measured 0.014° / 12.5 µm).
    true_height = [
        scan_cloud(
            np.load(r["gt"] / "height.npy"),
            r["normals"],
            r["mask"],
            r["albedo"],
            pixel_size_um=s.pixel_size_um,
            label=s.label,
            face=s.face,
            pose=s.pose,
        )
        for s, r in zip(scans, raw, strict=True)
    ]
    rot_deg, trans_mm = relative_errors(register_scans(true_height).transforms, truths)
    assert rot_deg < 0.05, rot_deg
    assert trans_mm < pixel_mm, trans_mm

    # 2. The reconstructed heights.
    reg = register_scans(scans)
    assert reg.init == ["pose"] * 6
    assert reg.restarts == []  # correct poses are not replaced by a turned start
    rot_deg, trans_mm = relative_errors(reg.transforms, truths)
    radius_mm = object_diameter_mm(scans) / 2
    # One pixel everywhere on the tablet: the translation, and the arc the rotation error
    # sweeps at the tablet's radius (measured ≤ 102 µm and 0.24° · 15 mm = 62 µm, pixel 214 µm).
    assert trans_mm < pixel_mm, trans_mm
    assert np.radians(rot_deg) * radius_mm < pixel_mm, rot_deg
    # Each face meets its four neighbours (the box's 12 edges). Their misfit is what the
    # heights' noise allows: reconstructed rim heights are off by ≤ 13 µm RMS (bench --rim),
    # two samples at ~45° to the normal give ≈ 13 µm along it (measured 2–7 µm inliers).
    used = [p for p in reg.pairs if p.used]
    assert len(used) == 12
    assert all(p.surface_rms_um < 13.0 for p in used), [p.surface_rms_um for p in used]

    # 3. An edge scan's recorded pose 20° wrong (issue 8) reaches the same poses (within the
    # same one-pixel bounds). This case once ended with the neighbouring edge rolled 15°.
    wrong = Rotation.from_rotvec(np.radians(20) * np.array([1.0, 0.0, -1.0]) / np.sqrt(2))
    right = [s.face for s in scans].index("right")
    bad = list(scans)
    bad[right] = dataclasses.replace(scans[right], pose=wrong.as_matrix() @ scans[right].pose)
    rot_bad, trans_bad = relative_errors(register_scans(bad).transforms, truths)
    assert trans_bad < pixel_mm, trans_bad
    assert np.radians(rot_bad) * radius_mm < pixel_mm, rot_bad


@pytest.mark.slow
def test_six_reconstructed_faces_at_107um_meet_the_goal(tmp_path):
    """Issue 8's criteria through the whole chain at 320×256 (107 µm pixels): relative poses
    under 0.05° and under one pixel (measured 0.018° / 12.2 µm on seed 0, ~35 CPU s), also
    with the bottom scan's recorded pose 20° wrong about (0, 1, 1) (~11 CPU s more): the one
    case of the sweep that once ended with the reverse tilted 16.8° into the tablet, inside
    every silhouette (now caught by the views' free space, joint.silhouette_consistency)."""
    scans, _, truths = _chain(tmp_path, size=(320, 256))
    pixel_mm = scans[0].pixel_size_um / 1000
    reg = register_scans(scans)
    assert reg.init == ["pose"] * 6
    rot_deg, trans_mm = relative_errors(reg.transforms, truths)
    assert rot_deg < 0.05, rot_deg
    assert trans_mm < pixel_mm, trans_mm

    wrong = Rotation.from_rotvec(np.radians(20) * np.array([0.0, 1.0, 1.0]) / np.sqrt(2))
    k = [s.face for s in scans].index("bottom")
    bad = list(scans)
    bad[k] = dataclasses.replace(scans[k], pose=wrong.as_matrix() @ scans[k].pose)
    rot_bad, trans_bad = relative_errors(register_scans(bad).transforms, truths)
    # The same criteria: a recovered pose reaches the same minimum as the true poses.
    assert rot_bad < 0.05, rot_bad
    assert trans_bad < pixel_mm, trans_bad
