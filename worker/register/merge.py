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
from PIL import Image

from worker.recon.glb import decimation_step
from worker.recon.gltf_frame import wrap_scene_in_gltf_frame
from worker.recon.mesh import grid_mesh as recon_grid_mesh
from worker.register.blend import face_weight
from worker.register.o3d import o3d, point_cloud, transform_points
from worker.register.pointcloud import ScanCloud

__all__ = [
    "face_normal_map",
    "grid_mesh",
    "merged_surface",
    "poisson_arrays",
    "poisson_off_the_gil",
    "scene_glb",
]


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
    vertices, triangles, normals, colours = poisson_off_the_gil(pts, nrm, col, depth, trim_quantile)
    rgba = np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(
        vertices, triangles, vertex_normals=normals, vertex_colors=rgba, process=False
    )


def poisson_arrays(
    pts: np.ndarray, nrm: np.ndarray, col: np.ndarray, depth: int, trim_quantile: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Screened Poisson surface of oriented, coloured points: (vertices (V, 3) mm, triangles
    (T, 3), vertex normals (V, 3), colours (V, 3) uint8), low-density vertices trimmed."""
    pcd = point_cloud(pts, nrm, col)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=depth, scale=1.1, linear_fit=False
    )
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, trim_quantile))
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    colours = np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255), 0, 255).astype(np.uint8)
    return (
        np.asarray(mesh.vertices),
        np.asarray(mesh.triangles),
        np.asarray(mesh.vertex_normals),
        colours,
    )


def poisson_off_the_gil(
    pts: np.ndarray, nrm: np.ndarray, col: np.ndarray, depth: int, trim_quantile: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`poisson_arrays` in a child process (`worker.register.poisson`): Open3D holds the GIL
    for the whole reconstruction, which stopped the job's heartbeat thread."""
    from worker.register.poisson import poisson_in_child

    return poisson_in_child(pts, nrm, col, depth, trim_quantile)


def grid_mesh(
    height_um: np.ndarray,
    mask: np.ndarray,
    albedo_rgb8: np.ndarray | None,
    *,
    pixel_size_um: float,
    max_triangles: int = 200_000,
) -> trimesh.Trimesh:
    """The scan's own surface (scan frame, mm) as SCAN_BUNDLE.md's mesh
    (`worker.recon.mesh.grid_mesh`, decimated to at most ``max_triangles``) with the image
    grid as TEXCOORD_0, u = (c + 0.5)/W, v = (r + 0.5)/H (as a face model's model.glb), so the
    face's full-resolution maps (`face_normal_map`, its albedo) map onto it; the albedo is the
    node's baseColorTexture (so a generic glTF viewer shows each face in colour)."""
    h = np.asarray(height_um, dtype=np.float64)
    rows, cols = h.shape
    step = decimation_step((rows, cols), max_triangles)
    mesh = recon_grid_mesh(h, mask, pixel_size_um=pixel_size_um, step=step)
    if len(mesh.faces) == 0:
        raise ValueError("mask: no triangle can be made (fewer than 3 adjacent pixels)")
    uv = np.stack([(mesh.cols + 0.5) / cols, (mesh.rows + 0.5) / rows], axis=1)
    # trimesh flips v on export (its uv origin is the bottom left, glTF's the top left).
    uv_trimesh = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)
    image = None
    if albedo_rgb8 is not None:
        alb = np.asarray(albedo_rgb8, np.uint8)
        alb = np.repeat(alb[..., None], 3, -1) if alb.ndim == 2 else alb[..., :3]
        image = Image.fromarray(np.ascontiguousarray(alb))
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=image, metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True
    )
    visual = trimesh.visual.TextureVisuals(uv=uv_trimesh, material=material)
    return trimesh.Trimesh(
        mesh.vertices_mm.astype(np.float64), mesh.faces, visual=visual, process=False
    )


def face_normal_map(
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    pixel_size_um: float,
    feather_mm: float = 0.5,
    weight: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W, 4) uint8: RGB = (n + 1)/2 of the scan-frame normals (as a face model's
    normals.png), A = 255·w, the face's quality weight (`worker.register.blend.face_weight`,
    computed from these normals unless ``weight`` is given, e.g. the face's own weight with
    normals blended across the seams). The viewer draws, in each overlap, the face of largest
    weight; with blended normals the faces agree there, so the change shows no seam.
    """
    n = np.asarray(normals, np.float64)
    m = np.asarray(mask, bool)
    w = face_weight(n, m, pixel_size_um=pixel_size_um, feather_mm=feather_mm)
    if weight is not None:
        if np.shape(weight) != m.shape:
            raise ValueError(f"weight must be (H, W) like the mask; got {np.shape(weight)}")
        w = np.asarray(weight, np.float64)
    ok = m & np.all(np.isfinite(n), axis=2)
    rgb = np.clip(np.rint((np.nan_to_num(n) + 1.0) * 127.5), 0, 255)
    rgb[~ok] = (128, 128, 0)  # (0, 0, -1): facing the camera, never drawn (weight 0)
    alpha = np.where(ok, np.rint(255 * np.clip(w, 0.0, 1.0)), 0)
    return np.concatenate([rgb, alpha[..., None]], axis=2).astype(np.uint8)


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
