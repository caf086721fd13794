"""Small bridges between numpy arrays and Open3D's point clouds (one place imports Open3D)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

__all__ = ["o3d", "point_cloud", "transform_points", "rigid"]

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


def point_cloud(
    points_mm: np.ndarray, normals: np.ndarray | None = None, colours: np.ndarray | None = None
) -> o3d.geometry.PointCloud:
    """An Open3D point cloud of (N, 3) points (copies; the arrays are not modified)."""
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.asarray(points_mm, dtype=np.float64))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    if colours is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colours, dtype=np.float64))
    return pcd


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 rigid transform to (N, 3) points: R·p + t."""
    t = np.asarray(transform, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


def rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The 4×4 matrix [R t; 0 1]."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out
