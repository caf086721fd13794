"""Synthetic scenes built from the formulas of SCAN_BUNDLE.md, with the `default` noise preset.

Noise preset `default`: 12-bit ADC, full well 20,000 e-, read noise 10 e-, fringe modulation
0.85.  A pixel whose linear radiance is x (fraction of full scale) collects x·20,000 e- with
Poisson statistics plus N(0, 10 e-) read noise, quantised to 4,095 levels, so that

    σ_x² = x / 20,000 + (10 / 20,000)² + (1 / 4,095)² / 12.

Helpers are fixtures returning plain functions so that tests can call them with their own
seeded generators.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

FULL_WELL_E = 20_000.0
READ_NOISE_E = 10.0
BIT_DEPTH = 12
MODULATION = 0.85


@dataclass(frozen=True)
class Scene:
    """A height field with analytic normals on an (H, W) grid; units µm."""

    height_um: np.ndarray
    normals: np.ndarray
    pixel_size_um: float


def sense(radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Linear radiance (fraction of full scale) → noisy, quantised linear radiance."""
    x = np.clip(np.asarray(radiance, dtype=np.float64), 0.0, None)
    electrons = rng.poisson(x * FULL_WELL_E) + rng.normal(0.0, READ_NOISE_E, x.shape)
    full = 2**BIT_DEPTH - 1
    dn = np.clip(np.round(electrons / FULL_WELL_E * full), 0, full)
    return (dn / full).astype(np.float32)


def sigma_of(radiance: np.ndarray) -> np.ndarray:
    """σ of :func:`sense` at linear radiance x (see module docstring)."""
    x = np.clip(np.asarray(radiance, dtype=np.float64), 0.0, None)
    full = 2**BIT_DEPTH - 1
    return np.sqrt(x / FULL_WELL_E + (READ_NOISE_E / FULL_WELL_E) ** 2 + 1.0 / (12 * full**2))


def sphere_scene(size: int = 64, *, radius_px: float = 40.0, pixel_size_um: float = 20.0) -> Scene:
    """A spherical cap centred in the image; outside the cap the plane h = 0.

    h = sqrt(R² − r²) − z0 with the cap cut at 60° slope; analytic normal
    n = (x − cx, y − cy, −sqrt(R² − r²)) / R (so n_z < 0, spec frame).
    """
    r_um = radius_px * pixel_size_um
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    dx = (xx - (size - 1) / 2) * pixel_size_um
    dy = (yy - (size - 1) / 2) * pixel_size_um
    rr2 = dx**2 + dy**2
    cut = (r_um * np.sin(np.deg2rad(60.0))) ** 2
    inside = rr2 <= cut
    zc = np.sqrt(np.clip(r_um**2 - rr2, 0.0, None))
    z0 = r_um * np.cos(np.deg2rad(60.0))
    height = np.where(inside, zc - z0, 0.0)
    normals = np.zeros((size, size, 3))
    normals[..., 2] = -1.0
    normals[inside] = np.stack([dx[inside], dy[inside], -zc[inside]], axis=1) / r_um
    return Scene(height_um=height, normals=normals, pixel_size_um=pixel_size_um)


def lights(azimuth_deg, polar_deg) -> np.ndarray:
    phi = np.deg2rad(np.asarray(azimuth_deg, dtype=np.float64))
    th = np.deg2rad(np.broadcast_to(np.asarray(polar_deg, dtype=np.float64), phi.shape))
    return np.stack([np.sin(th) * np.sin(phi), np.sin(th) * np.cos(phi), -np.cos(th)], axis=1)


@pytest.fixture
def recon_sense():
    return sense


@pytest.fixture
def recon_sigma():
    return sigma_of


@pytest.fixture
def recon_sphere():
    return sphere_scene


@pytest.fixture
def recon_lights():
    return lights


@pytest.fixture
def recon_noise():
    return {
        "full_well_e": FULL_WELL_E,
        "read_noise_e": READ_NOISE_E,
        "bit_depth": BIT_DEPTH,
        "modulation": MODULATION,
    }
