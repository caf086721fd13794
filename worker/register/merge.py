"""The registered scans as one model: a scene with one mesh per scan (the paper shows the
faces so) and one merged, coloured surface.

Merged surface: screened Poisson reconstruction (Kazhdan & Hoppe, "Screened Poisson surface
reconstruction", ACM ToG 2013; Open3D ``create_from_point_cloud_poisson``) of all scans'
oriented, coloured points in the tablet frame; vertices whose Poisson density is in the
lowest ``trim_quantile`` (surface invented far from any sample) may be removed. The default
keeps them all: the scans of a whole tablet cover it, and the lowest densities are where
steep wedge walls were left out of the scans (points tilted > 70°), so trimming made holes.
"""

from __future__ import annotations

import numpy as np
import trimesh

from worker.recon.gltf_frame import wrap_scene_in_gltf_frame
from worker.register.o3d import o3d, point_cloud, transform_points
from worker.register.pointcloud import ScanCloud

__all__ = ["grid_mesh", "merged_surface", "scene_glb"]


def merged_surface(
    scans: list[ScanCloud],
    transforms: list[np.ndarray],
    *,
    depth: int = 9,
    trim_quantile: float = 0.0,
) -> trimesh.Trimesh:
    """Watertight-ish mesh (mm, tablet frame) with vertex colours (uint8 RGBA) and normals."""
    if len(scans) != len(transforms) or not scans:
        raise ValueError("scans and transforms must be non-empty and of equal length")
    if not 5 <= depth <= 12:
        raise ValueError(f"depth must be 5..12, got {depth}")
    pts = np.concatenate(
        [transform_points(t, s.points_mm) for s, t in zip(scans, transforms, strict=True)]
    )
    nrm = np.concatenate([s.normals @ t[:3, :3].T for s, t in zip(scans, transforms, strict=True)])
    col = np.concatenate([s.colours for s in scans])
    pcd = point_cloud(pts, nrm, col)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=depth, scale=1.1, linear_fit=False
    )
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, trim_quantile))
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    colours = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255), 0, 255).astype(np.uint8)
    rgba = np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(
        np.asarray(mesh.vertices),
        np.asarray(mesh.triangles),
        vertex_normals=np.asarray(mesh.vertex_normals),
        vertex_colors=rgba,
        process=False,
    )


def grid_mesh(
    height_um: np.ndarray,
    mask: np.ndarray,
    albedo_rgb8: np.ndarray | None,
    *,
    pixel_size_um: float,
    max_triangles: int = 200_000,
) -> trimesh.Trimesh:
    """The scan's own surface (scan frame, mm) as SCAN_BUNDLE.md's mesh, decimated by taking
    every k-th row and column so that it has at most ``max_triangles``; vertex colours."""
    h = np.asarray(height_um, dtype=np.float64)
    ok = np.asarray(mask, bool) & np.isfinite(h)
    rows, cols = h.shape
    step = 1
    while 2 * ((rows - 1) // step) * ((cols - 1) // step) > max_triangles:
        step += 1
    r = np.arange(0, rows, step)
    c = np.arange(0, cols, step)
    sub_ok = ok[np.ix_(r, c)]
    index = -np.ones(sub_ok.shape, np.int64)
    index[sub_ok] = np.arange(sub_ok.sum())
    rr, cc = np.meshgrid(r, c, indexing="ij")
    s_mm = pixel_size_um / 1000.0
    verts = np.stack(
        [cc[sub_ok] * s_mm, rr[sub_ok] * s_mm, -h[rr[sub_ok], cc[sub_ok]] / 1000.0], -1
    )
    a, b = index[:-1, :-1], index[1:, :-1]
    d, e = index[:-1, 1:], index[1:, 1:]
    # (r,c) → (r+1,c) → (r,c+1) has its right-hand normal toward −z, the camera.
    tris = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([d, b, e], -1).reshape(-1, 3)]
    )
    tris = tris[np.all(tris >= 0, axis=1)]
    if albedo_rgb8 is None:
        rgb = np.full((len(verts), 3), 160, np.uint8)
    else:
        alb = np.asarray(albedo_rgb8)
        rgb = alb[rr[sub_ok], cc[sub_ok]]
        rgb = np.repeat(rgb[:, None], 3, 1) if rgb.ndim == 1 else rgb[:, :3]
    rgba = np.concatenate([rgb.astype(np.uint8), np.full((len(verts), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(verts, tris, vertex_colors=rgba, process=False)


def scene_glb(meshes: dict[str, trimesh.Trimesh], transforms: dict[str, np.ndarray]) -> bytes:
    """glTF 2.0 binary with one node per scan named by its label, each carrying its scan →
    tablet transform (mm), so that a viewer can show or hide each face; all under one root node
    in glTF's convention (metres, +Y up, the tablet's frame facing +Z: `gltf_frame`)."""
    if set(meshes) != set(transforms):
        raise ValueError("meshes and transforms must have the same labels")
    scene = trimesh.Scene()
    for label, mesh in meshes.items():
        scene.add_geometry(mesh, node_name=label, geom_name=label, transform=transforms[label])
    return wrap_scene_in_gltf_frame(scene.export(file_type="glb"))
