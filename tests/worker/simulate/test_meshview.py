"""Scanning an arbitrary triangle mesh (trimesh file) instead of the synthetic tablet."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from worker.bundle import validate_bundle
from worker.simulate.meshview import load_mesh, render_mesh_view
from worker.simulate.scan import simulate_scan

R_MM, S_UM = 10.0, 300.0


@pytest.fixture
def sphere_file(tmp_path):
    path = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=4, radius=R_MM).export(path)
    return path


def test_sphere_heights_and_normals(sphere_file):
    view = render_mesh_view(
        load_mesh(sphere_file), np.eye(3), width=100, height=80, pixel_size_um=S_UM, supersample=2
    )
    gt = view.ground_truth()
    h, n, mask = gt["height"].astype(float), gt["normals"].astype(float), gt["mask"]
    r = np.hypot(
        np.arange(100)[None, :] * S_UM - 49.5 * S_UM, np.arange(80)[:, None] * S_UM - 39.5 * S_UM
    )
    inner = mask & (r < 0.8 * R_MM * 1000)
    true = np.sqrt(np.maximum((R_MM * 1000) ** 2 - r**2, 0))
    offset = np.median((h - true)[inner])
    # Bound: flat triangles of edge e ≈ 0.078·R lie up to the sagitta e²/(8R) ≈ 7.6 µm inside
    # the sphere; 10 µm allows for the pixel box.
    assert np.max(np.abs(h - true - offset)[inner]) < 10.0
    # Outward normals of the visible cap face the camera and match the sphere's within the
    # facet angle e/R ≈ 4.5°.
    expected = np.stack(
        [
            (np.arange(100)[None, :] - 49.5) * S_UM * np.ones((80, 1)),
            (np.arange(80)[:, None] - 39.5) * S_UM * np.ones((1, 100)),
            -true,
        ],
        -1,
    )
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.sum(n * expected, -1), -1, 1)))[inner]
    assert np.all(ang < 4.5)


def test_scan_of_a_mesh_file_validates(tmp_path, sphere_file):
    result = simulate_scan(
        tmp_path / "out", mesh=sphere_file, size=(32, 24), noise="clean", as_zip=True
    )
    assert validate_bundle(result.bundles["obverse"]) == []
    assert np.load(result.gt_dirs["obverse"] / "mask.npy").mean() > 0.2


def test_unreadable_mesh_is_a_value_error(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_text("not a mesh")
    with pytest.raises(ValueError, match="mesh"):
        load_mesh(bad)
