"""Pure functions of worker.register on synthetic point clouds with known transforms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from worker.register.align import cloud_of, feature_alignment, icp
from worker.register.fatcross import (
    FATCROSS_VIEWS,
    add_scale_bar,
    compose_fatcross,
    render_orthographic,
)
from worker.register.merge import grid_mesh, merged_surface
from worker.register.o3d import rigid, transform_points
from worker.register.pointcloud import ScanCloud, scan_cloud


def _bumpy_sphere(rng, n=6000, radius_mm=10.0):
    """Points on a sphere with a few Gaussian bumps (so that no rotation is degenerate)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centres = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-0.6, 0.8, 0], [0.3, -0.3, -0.9]])
    centres = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    r = radius_mm + sum(
        1.5 * np.exp(-np.sum((d - c) ** 2, 1) / 0.08) * (k + 1) / 3 for k, c in enumerate(centres)
    )
    return d * r[:, None]


def _cloud(points, label="a"):
    from worker.register.o3d import point_cloud

    pcd = point_cloud(points)
    pcd.estimate_normals()
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    normals = -np.asarray(pcd.normals)  # outward
    return ScanCloud(points, normals, np.full_like(points, 0.5), 100.0, label)


def test_scan_cloud_places_pixels_as_the_spec_says():
    h = np.full((20, 30), 500.0)
    h[0, 0] = np.nan
    n = np.zeros((20, 30, 3))
    n[..., 2] = -1.0
    c = scan_cloud(h, n, np.ones((20, 30), bool), None, pixel_size_um=50.0, label="x", erode_px=0)
    # pixel (r, c) → (c·s, r·s, −h) µm, in mm
    assert c.points_mm.shape == (20 * 30 - 1, 3)
    assert np.allclose(c.points_mm[0], [0.05, 0.0, -0.5])  # (0, 1): first finite pixel
    assert np.allclose(c.points_mm[-1], [29 * 0.05, 19 * 0.05, -0.5])


def test_scan_cloud_rejects_bad_input():
    h = np.zeros((20, 30))
    n = np.zeros((20, 30, 3))
    n[..., 2] = -1
    with pytest.raises(ValueError, match="pixel_size_um"):
        scan_cloud(h, n, np.ones((20, 30), bool), None, pixel_size_um=0, label="x")
    with pytest.raises(ValueError, match="normals"):
        scan_cloud(h, n[:, :5], np.ones((20, 30), bool), None, pixel_size_um=1, label="x")
    with pytest.raises(ValueError, match="pose"):
        scan_cloud(
            h, n, np.ones((20, 30), bool), None, pixel_size_um=1, label="x", pose=np.ones((3, 3))
        )


def test_icp_recovers_a_small_transform():
    rng = np.random.default_rng(1)
    pts = _bumpy_sphere(rng)
    truth = rigid(
        Rotation.from_euler("xyz", [4, -3, 5], degrees=True).as_matrix(), [0.4, -0.3, 0.2]
    )
    moved = transform_points(truth, pts)
    a = _cloud(pts)
    b = _cloud(moved, "b")
    res = icp(cloud_of(a), cloud_of(b), np.eye(4), distances_mm=(3.0, 1.0, 0.3))
    # Identical noise-free samples: the error is the solver's, far below 1e-3 mm / 1e-3°.
    err = np.linalg.inv(truth) @ res.transform
    assert np.linalg.norm(err[:3, 3]) < 1e-3
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 1e-2
    assert res.fitness > 0.99


def test_feature_alignment_needs_no_pose():
    rng = np.random.default_rng(2)
    pts = _bumpy_sphere(rng, n=8000)
    truth = rigid(
        Rotation.from_euler("xyz", [70, -120, 40], degrees=True).as_matrix(), [5.0, 2.0, -3.0]
    )
    # Different samples of the same surface (a fresh draw), so features must generalise.
    other = _bumpy_sphere(np.random.default_rng(3), n=8000)
    a = cloud_of(_cloud(pts))
    b = cloud_of(_cloud(transform_points(truth, other), "b"))
    t = feature_alignment(a, b, voxel_mm=0.8, seed=0)
    res = icp(a, b, t, distances_mm=(2.0, 0.8, 0.4))
    err = np.linalg.inv(truth) @ res.transform
    # Two independent samplings with mean spacing ~0.5 mm: ICP residual misfit is a fraction
    # of the spacing; 0.2 mm and 1° are several times the expected error.
    assert np.linalg.norm(err[:3, 3]) < 0.2
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 1.0


def test_merged_surface_of_a_sphere_lies_on_it():
    rng = np.random.default_rng(4)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scan = ScanCloud(10.0 * d, d, np.full_like(d, 0.5), 100.0, "s")
    mesh = merged_surface([scan], [np.eye(4)], depth=7)
    r = np.linalg.norm(mesh.vertices, axis=1)
    # depth 7 over ~22 mm: cells of ~0.17 mm; Poisson's iso-surface lies within a cell.
    assert np.sqrt(np.mean((r - 10.0) ** 2)) < 0.17
    assert len(mesh.faces) > 1000


def test_grid_mesh_faces_point_to_the_camera():
    h = np.zeros((10, 12))
    m = grid_mesh(h, np.ones((10, 12), bool), None, pixel_size_um=100.0)
    assert len(m.faces) == 2 * 9 * 11
    assert np.all(m.face_normals[:, 2] < -0.99)


def test_render_orthographic_and_fatcross_layout():
    import trimesh

    box = trimesh.creation.box(extents=(30.0, 20.0, 6.0))
    colours = np.full((len(box.vertices), 4), 200, np.uint8)
    px = 4.0
    views = {
        k: render_orthographic(
            box.vertices, box.faces, colours, box.vertex_normals, r, px_per_mm=px
        )
        for k, r in FATCROSS_VIEWS.items()
    }
    # The obverse shows 30 × 20 mm, the top edge 30 × 6, the left edge 6 × 20 (pixels ±1).
    assert abs(views["o"]["mask"].shape[1] - 30 * px) <= 1
    assert abs(views["o"]["mask"].shape[0] - 20 * px) <= 1
    assert abs(views["te"]["mask"].shape[0] - 6 * px) <= 1
    assert abs(views["le"]["mask"].shape[1] - 6 * px) <= 1
    assert views["o"]["mask"].mean() > 0.9
    # The obverse face of the box is at z = -3 mm: height toward the camera 3000 µm.
    assert np.allclose(np.nanmedian(views["o"]["height_um"]), 3000.0, atol=1.0)
    imgs = {
        k: (255 * v["mask"][..., None].repeat(3, -1)).astype(np.uint8) for k, v in views.items()
    }
    plate = compose_fatcross(imgs, gap_px=5)
    w = imgs["le"].shape[1] + imgs["o"].shape[1] + imgs["re"].shape[1] + 10
    h = sum(imgs[k].shape[0] for k in ("te", "o", "be", "r")) + 15
    assert plate.shape == (h, w, 3)
    with_bar = add_scale_bar(plate, px_per_mm=px)
    assert with_bar.shape[0] > plate.shape[0]
    with pytest.raises(ValueError, match="missing"):
        compose_fatcross({"o": imgs["o"]}, gap_px=1)


def test_face_normal_map_weight_falls_to_zero_at_the_rim_and_with_tilt():
    from worker.register.merge import face_normal_map

    mask = np.zeros((40, 50), bool)
    mask[5:35, 5:45] = True
    n = np.zeros((40, 50, 3))
    n[..., 2] = -1.0
    tilt = np.radians(60)
    n[20:, 25:] = (np.sin(tilt), 0.0, -np.cos(tilt))
    rgba = face_normal_map(n, mask, pixel_size_um=100.0, feather_mm=0.5)  # feather 5 px
    assert rgba.shape == (40, 50, 4) and rgba.dtype == np.uint8
    np.testing.assert_array_equal(rgba[12, 12, :3], [128, 128, 0])  # (0, 0, -1)
    assert rgba[12, 12, 3] == 255  # 7 px inside, facing the camera
    assert rgba[5, 20, 3] == 51  # on the rim row: 1 px from off-mask, 1/5
    assert rgba[0, 0, 3] == 0  # off the mask
    # cos² 60° = 1/4 on the tilted patch, well inside the mask.
    assert abs(int(rgba[27, 32, 3]) - 64) <= 1


def test_grid_mesh_carries_the_image_grid_as_texture_coordinates():
    import pygltflib
    import trimesh

    from worker.register.merge import scene_glb

    h = np.zeros((10, 12))
    albedo = np.full((10, 12, 3), 90, np.uint8)
    m = grid_mesh(h, np.ones((10, 12), bool), albedo, pixel_size_um=100.0)
    glb = scene_glb({"obverse": m}, {"obverse": np.eye(4)})
    gltf = pygltflib.GLTF2.load_from_bytes(glb)
    prim = gltf.meshes[0].primitives[0]
    assert prim.attributes.TEXCOORD_0 is not None
    assert gltf.materials[prim.material].pbrMetallicRoughness.baseColorTexture is not None
    loaded = trimesh.load(trimesh.util.wrap_as_stream(glb), file_type="glb", force="mesh")
    uv = loaded.visual.uv
    # Pixel (r, c) at u = (c + 0.5)/W, v = (r + 0.5)/H (glTF's v down, trimesh's v up).
    np.testing.assert_allclose(uv[:, 0].min(), 0.5 / 12, atol=1e-6)
    np.testing.assert_allclose(uv[:, 0].max(), 11.5 / 12, atol=1e-6)
    np.testing.assert_allclose(1 - uv[:, 1].max(), 0.5 / 10, atol=1e-6)
