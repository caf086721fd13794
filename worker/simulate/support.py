"""What the tablet lies on, and the clay's reflectance scale: scene changes to a View.

The ideal scene is a dark matte velvet plane 3 mm below the tablet (``view.py``). Real
rigs hold the tablet in a V-block (two inclined planes, a matte grained material) or on a
cloth (folds and a woven texture); both are brighter than velvet and textured, so they
show in every frame. They replace the background samples only: the tablet, the gt mask
and the gt heights are unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from worker.simulate.view import View, sample_coords_um

__all__ = ["scale_albedo", "with_support"]


def scale_albedo(view: View, scale: float) -> View:
    """The view with the tablet's reflectance multiplied by ``scale`` (clipped to 0.95)."""
    if scale == 1.0:
        return view
    albedo = view.albedo_ss.copy()
    albedo[view.tablet_ss] = np.clip(albedo[view.tablet_ss] * np.float32(scale), 0.0, 0.95)
    return dataclasses.replace(view, albedo_ss=albedo, cache={})


def _normals(h_um: np.ndarray, step_um: float) -> np.ndarray:
    gy, gx = np.gradient(h_um.astype(np.float64), step_um)
    g = np.stack([-gx, -gy, -np.ones_like(gx)], -1)
    return (g / np.linalg.norm(g, axis=-1, keepdims=True)).astype(np.float32)


def _vblock(xs, ys, rng, floor_um, top_um):
    """Two planes meeting in a groove along x under the tablet; grain along the groove."""
    yc = 0.5 * (ys[0] + ys[-1]) + rng.uniform(-0.05, 0.05) * (ys[-1] - ys[0])
    half = 0.5 * (ys[-1] - ys[0])
    rise = rng.uniform(0.6, 1.0) * (top_um - floor_um)
    dist = np.abs(ys - yc)[:, None] / half
    h = floor_um + rise * np.minimum(dist, 1.0) + 0.0 * xs[None, :]
    grain = np.zeros_like(h)
    for _ in range(6):
        k = 2 * np.pi / rng.uniform(150.0, 1500.0)
        grain += np.sin(
            k * ys[:, None] + rng.uniform(0, 0.3) * k * xs[None, :] + rng.uniform(0, 6.3)
        )
    albedo = rng.uniform(0.25, 0.6) * (1 + 0.04 * grain)
    tint = np.array([1.0, 0.9, 0.75]) ** rng.uniform(0.0, 2.0)
    return h, albedo[..., None] * tint


def _cloth(xs, ys, rng, floor_um, top_um):
    """Soft folds (wavelengths 3-12 mm) and a woven texture (threads 0.3-0.6 mm)."""
    h = np.full((len(ys), len(xs)), floor_um)
    amp = rng.uniform(0.1, 0.3) * (top_um - floor_um)
    for _ in range(4):
        k = 2 * np.pi / rng.uniform(3000.0, 12_000.0)
        a = rng.uniform(0, np.pi)
        h += (
            amp
            / 2
            * np.sin(k * (np.cos(a) * xs[None, :] + np.sin(a) * ys[:, None]) + rng.uniform(0, 6.3))
        )
    thread = rng.uniform(300.0, 600.0)
    weave = np.sin(2 * np.pi * xs / thread)[None, :] * np.sin(2 * np.pi * ys / thread)[:, None]
    h += 15.0 * weave
    albedo = rng.uniform(0.1, 0.5) * (1 + 0.15 * weave)
    tint = rng.uniform(0.6, 1.0, 3)
    return h, albedo[..., None] * tint


def with_support(view: View, support: str, seed: int) -> View:
    """The view with the background replaced by ``support`` (``velvet``: unchanged).

    The support lies below the tablet's lowest visible point (its floor 1-3 mm below) and
    rises at most to that point's height, so it never hides the tablet; drawn from seed.
    """
    if support == "velvet":
        return view
    makers = {"vblock": _vblock, "cloth": _cloth}
    if support not in makers:
        raise ValueError(f"support: unknown {support!r}; choose from ['velvet', *{sorted(makers)}]")
    rng = np.random.default_rng([seed, 0x5 if support == "vblock" else 0x6, 0x5BB])
    xs = sample_coords_um(view.width, view.pixel_size_um, view.supersample)
    ys = sample_coords_um(view.height, view.pixel_size_um, view.supersample)
    on = view.tablet_ss
    lowest = float(view.height_ss_um[on].min())
    floor = lowest - rng.uniform(1000.0, 3000.0)
    h_bg, albedo_bg = makers[support](xs, ys, rng, floor, lowest)
    h_bg = np.minimum(h_bg, lowest)
    height = np.where(on, view.height_ss_um, h_bg).astype(np.float32)
    normals = np.where(on[..., None], view.normals_ss, _normals(h_bg, view.sample_step_um))
    albedo = np.where(on[..., None], view.albedo_ss, np.clip(albedo_bg, 0.02, 0.95))
    return dataclasses.replace(
        view,
        height_ss_um=height,
        normals_ss=normals.astype(np.float32),
        albedo_ss=albedo.astype(np.float32),
        cache={},
    )
