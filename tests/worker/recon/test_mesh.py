"""Meshes (worker.recon.mesh, worker.recon.glb): winding, coordinates, PLY and GLB files."""

import io

import numpy as np
import pygltflib
import pytest
import trimesh

from worker.recon.glb import decimation_step, glb_bytes, tangent_space_normals
from worker.recon.mesh import grid_mesh, ply_bytes, vertex_normals

S_UM = 25.0


def test_vertices_are_in_mm_in_the_spec_frame():
    h = np.array([[10.0, 20.0], [30.0, 40.0]], np.float32)
    mesh = grid_mesh(h, np.ones((2, 2), bool), pixel_size_um=S_UM)
    np.testing.assert_allclose(
        mesh.vertices_mm,
        [[0, 0, -0.01], [0.025, 0, -0.02], [0, 0.025, -0.03], [0.025, 0.025, -0.04]],
        rtol=1e-6,
    )


def test_faces_face_the_camera_including_rim_triangles():
    rng = np.random.default_rng(0)
    h = rng.normal(0, 1, (20, 24)).astype(np.float32)  # nearly flat: all normals toward −z
    mask = np.ones(h.shape, bool)
    mask[0, 0] = mask[5, 7] = mask[19, 23] = mask[10, 0] = False  # cells with 3 corners
    mesh = grid_mesh(h, mask, pixel_size_um=S_UM)
    v = mesh.vertices_mm.astype(np.float64)
    f = mesh.faces
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert np.all(normal[:, 2] < 0)
    full_cells = 19 * 23
    # A missing pixel turns the cells it is a corner of (1 at an image corner, 2 on an edge, 4
    # inside) into three-corner cells, each of one triangle instead of two.
    touched = 1 + 4 + 1 + 2
    assert len(f) == 2 * full_cells - touched
    assert np.all(vertex_normals(mesh.vertices_mm, f)[:, 2] < 0)


def test_ply_round_trips_through_trimesh():
    y, x = np.mgrid[0:12, 0:16]
    h = (5.0 * x - 3.0 * y).astype(np.float32)
    mask = np.ones(h.shape, bool)
    mesh = grid_mesh(h, mask, pixel_size_um=S_UM)
    vn = vertex_normals(mesh.vertices_mm, mesh.faces)
    colors = np.tile(np.array([[200, 100, 50]], np.uint8), (len(vn), 1))
    data = ply_bytes(mesh.vertices_mm, mesh.faces, normals=vn, colors_rgb8=colors)
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    tm = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    np.testing.assert_allclose(tm.vertices, mesh.vertices_mm, rtol=1e-6)
    np.testing.assert_array_equal(tm.faces, mesh.faces)
    np.testing.assert_array_equal(tm.visual.vertex_colors[:, :3], colors)
    # Surface normal of the plane h = 5x − 3y (per pixel): n ∝ (−5/s, 3/s, −1) in the spec frame.
    want = np.array([-5 / S_UM, 3 / S_UM, -1.0])
    np.testing.assert_allclose(
        tm.face_normals, np.tile(want / np.linalg.norm(want), (len(tm.faces), 1)), atol=1e-5
    )


def test_decimation_step_bounds_the_triangles():
    step = decimation_step((1024, 1280), 200_000)
    assert step == 4
    assert 2 * (1023 // step + 1) * (1279 // step + 1) <= 200_000


def test_tangent_space_normal_of_the_mesh_itself_is_up():
    n = np.zeros((8, 8, 3))
    n[..., 2] = -1
    grid = np.zeros((3, 3, 3))
    grid[..., 2] = -1
    ts = tangent_space_normals(n, grid, np.array([0, 4, 7]), np.array([0, 4, 7]))
    np.testing.assert_allclose(ts[..., 2], 1.0, atol=1e-6)
    # A normal tilted toward +x (the image right) has a positive tangent component.
    n2 = n.copy()
    n2[..., 0] = 0.1
    n2 /= np.linalg.norm(n2, axis=-1, keepdims=True)
    assert np.all(
        tangent_space_normals(n2, grid, np.array([0, 4, 7]), np.array([0, 4, 7]))[..., 0] > 0.09
    )


def test_glb_is_valid_gltf_with_textures_and_image_grid_uvs():
    rows, cols = 40, 50
    y, x = np.mgrid[0:rows, 0:cols]
    h = (2.0 * x).astype(np.float32)
    mask = np.ones((rows, cols), bool)
    n = np.zeros((rows, cols, 3), np.float32)
    n[..., 2] = -1
    albedo = np.full((rows, cols, 3), 120, np.uint8)
    data, info = glb_bytes(h, mask, n, albedo, pixel_size_um=S_UM, max_triangles=800)
    assert info["triangles"] <= 800
    gltf = pygltflib.GLTF2.load_from_bytes(data)
    assert gltf.asset.version == "2.0"
    assert len(gltf.images) == 2
    mat = gltf.materials[0]
    assert mat.pbrMetallicRoughness.baseColorTexture.index == 0
    assert mat.normalTexture.index == 1
    scene = trimesh.load(io.BytesIO(data), file_type="glb")
    geom = next(iter(scene.geometry.values()))
    # Same mm coordinates as the PLY: x = c·s/1000 spans the image width.
    assert geom.vertices[:, 0].max() == pytest.approx((cols - 1) * S_UM / 1000, rel=1e-6)
    uv = geom.visual.uv
    # trimesh flips v on import (OpenGL convention): v_gltf = 1 − v_trimesh.
    assert uv[:, 0].min() == pytest.approx(0.5 / cols, rel=1e-5)
    assert (1 - uv[:, 1]).max() == pytest.approx((rows - 0.5) / rows, rel=1e-5)


def test_glb_cross_product_is_numpys():
    # The tangent frames' B = N × T: the same values as np.cross, NaN included.
    from worker.recon.glb import _cross

    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        a = rng.normal(size=(7, 5, 3)).astype(dtype)
        b = rng.normal(size=(7, 5, 3)).astype(dtype)
        a[0, 0, 1] = np.nan
        np.testing.assert_array_equal(_cross(a, b), np.cross(a, b))
        assert _cross(a, b).dtype == dtype


def test_glb_takes_the_albedo_png_the_caller_encoded():
    # model_dir hands over albedo.png's bytes: the same GLB as encoding the albedo here.
    import cv2

    rng = np.random.default_rng(1)
    rows, cols = 30, 40
    h = rng.normal(0, 5, (rows, cols)).astype(np.float32)
    mask = np.ones((rows, cols), bool)
    n = np.zeros((rows, cols, 3), np.float32)
    n[..., 2] = -1
    albedo = rng.integers(0, 256, (rows, cols, 3), dtype=np.uint8)
    png = cv2.imencode(".png", np.ascontiguousarray(albedo[..., ::-1]))[1].tobytes()
    plain = glb_bytes(h, mask, n, albedo, pixel_size_um=S_UM, max_triangles=800)
    given = glb_bytes(h, mask, n, albedo, pixel_size_um=S_UM, max_triangles=800, albedo_png=png)
    assert given == plain


def test_tangent_space_normals_and_glb_do_not_depend_on_the_row_blocks(monkeypatch):
    from worker.recon import glb

    rng = np.random.default_rng(2)
    rows, cols = 37, 29
    h = rng.normal(0, 20, (rows, cols)).astype(np.float32)
    mask = np.ones((rows, cols), bool)
    mask[:4, :6] = False
    n = rng.normal(size=(rows, cols, 3)).astype(np.float32)
    n[..., 2] = -np.abs(n[..., 2]) - 0.5
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[5, 7] = np.nan
    albedo = rng.integers(0, 256, (rows, cols, 3), dtype=np.uint8)
    grid = rng.normal(size=(5, 4, 3)).astype(np.float32)
    rs, cs = np.array([0, 9, 18, 27, 36]), np.array([0, 9, 18, 28])
    whole_n = tangent_space_normals(n, grid, rs, cs)
    whole_glb = glb_bytes(h, mask, n, albedo, pixel_size_um=S_UM, max_triangles=300)
    monkeypatch.setattr(glb, "_BLOCK_PX", 2 * cols + 1)  # blocks of 2 rows, one of 1 at the end
    np.testing.assert_array_equal(tangent_space_normals(n, grid, rs, cs), whole_n)
    assert glb_bytes(h, mask, n, albedo, pixel_size_um=S_UM, max_triangles=300) == whole_glb
