"""Shared synthetic shading cases for the photometric tests (tests/worker/measure and
tests/worker/recon): a sphere cap of known normals and the angle between normal maps."""

import numpy as np


def sphere_normals(size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (size, size, 3) of a sphere cap with slopes up to 53° (n_z < 0, the spec's
    convention), flat outside, and the mask of the cap."""
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    c, r = (size - 1) / 2, 0.45 * size
    dx, dy = (xx - c) / r, (yy - c) / r
    inside = dx**2 + dy**2 < 0.8**2
    n = np.stack([dx, dy, -np.sqrt(np.clip(1 - dx**2 - dy**2, 0, None))], -1)
    n[~inside] = (0.0, 0.0, -1.0)
    return n, inside


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit vectors along the last axis."""
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))
