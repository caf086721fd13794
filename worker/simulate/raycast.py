"""First intersection of rays with a carved tablet (pillow minus convex cavities).

The solid is ``{f(x) <= 0} minus the union of cavities``; each cavity is a convex
polyhedron ``{x : n_k·x <= c_k for all k}`` (air). Along a ray the first solid point is
found by sphere tracing the smooth body, a few Newton steps on the rough body, then
jumping over every cavity that contains the current point (to the cavity's exit
facet, which is then the visible surface with exact normal ``-n_k``), repeated until
the point is in the body and in no cavity.

Everything in the tablet frame, µm.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from worker.simulate.pillow import Pillow

__all__ = ["Cavities", "Hits", "cast_rays"]

_HIT_TOL_UM = 0.05
_MAX_MARCH = 96


@dataclass(frozen=True)
class Cavities:
    """Convex cavities, padded to the same number of planes.

    normals: (K, P, 3) unit, pointing out of the cavity (into the clay);
    offsets_um: (K, P); padding planes have normal 0 and offset 1 (always satisfied);
    centres_um: (K, 3) and radii_um: (K,) bound each cavity's carved part (a sphere).
    """

    normals: np.ndarray
    offsets_um: np.ndarray
    centres_um: np.ndarray
    radii_um: np.ndarray

    @staticmethod
    def empty() -> Cavities:
        return Cavities(np.zeros((0, 1, 3)), np.zeros((0, 1)), np.zeros((0, 3)), np.zeros(0))

    @staticmethod
    def from_polyhedra(
        planes: Sequence[tuple[np.ndarray, np.ndarray]],
        centres_um: np.ndarray,
        radii_um: np.ndarray,
    ) -> Cavities:
        """From a list of (normals (P_i, 3), offsets (P_i,)) per cavity."""
        if not planes:
            return Cavities.empty()
        width = max(len(o) for _, o in planes)
        normals = np.zeros((len(planes), width, 3))
        offsets = np.ones((len(planes), width))
        for i, (n, o) in enumerate(planes):
            normals[i, : len(o)] = n
            offsets[i, : len(o)] = o
        return Cavities(
            normals, offsets, np.asarray(centres_um, float), np.asarray(radii_um, float)
        )

    def __len__(self) -> int:
        return len(self.offsets_um)


@dataclass(frozen=True)
class Hits:
    """Result of ``cast_rays`` for N rays: t (N,) µm (inf on a miss), hit (N,) bool,
    normals (N, 3) outward unit normals of the solid (NaN on a miss), facet (N,) the index
    of the cavity whose facet was hit (-1 on the rough body)."""

    t_um: np.ndarray
    hit: np.ndarray
    normals: np.ndarray
    facet: np.ndarray


def _march_body(
    pillow: Pillow, origins: np.ndarray, dirs: np.ndarray, t0: np.ndarray, t_far: np.ndarray
) -> np.ndarray:
    """Sphere trace the smooth body from t0; returns t of the hit or inf."""
    t = t0.copy()
    # A ray restarted beyond the bounding box (it left a cavity there) meets nothing more.
    t[t > t_far] = np.inf
    active = np.flatnonzero(t < t_far)
    for _ in range(_MAX_MARCH):
        if active.size == 0:
            break
        d = dirs if dirs.ndim == 1 else dirs[active]
        dist = pillow.smooth_sdf(origins[active] + t[active, None] * d)
        # 0.9: the bulge makes f a slightly-more-than-Lipschitz-1 bound.
        t[active] += np.maximum(0.9 * dist, 0.0)
        done = dist < _HIT_TOL_UM
        gone = t[active] > t_far[active]
        t[active[gone & ~done]] = np.inf
        active = active[~done & ~gone]
    t[active] = np.inf
    return t


def _newton_rough(
    pillow: Pillow, origins: np.ndarray, dirs: np.ndarray, t: np.ndarray, steps: int = 3
) -> np.ndarray:
    """Refine body hits (t finite) onto the rough surface f = 0 along each ray."""
    idx = np.flatnonzero(np.isfinite(t))
    t = t.copy()
    for _ in range(steps):
        if idx.size == 0:
            break
        d = dirs if dirs.ndim == 1 else dirs[idx]
        f, slope = pillow.sdf_and_slope(origins[idx] + t[idx, None] * d, d)
        # Grazing rays have tiny slopes; limit the step to the roughness scale.
        step = np.clip(-f / np.minimum(slope, -0.05), -50.0, 50.0)
        t[idx] += step
    return t


def _cavity_intervals(
    cav: Cavities, i: int, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry t, exit t and exit-plane index of each ray through cavity i."""
    n = cav.normals[i]
    num = cav.offsets_um[i][None, :] - origins @ n.T  # (M, P)
    den = (dirs @ n.T)[None, :] if dirs.ndim == 1 else dirs @ n.T
    den = np.broadcast_to(den, num.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = num / den
    t_in = np.max(np.where(den < 0, ratio, -np.inf), axis=1)
    upper = np.where(den > 0, ratio, np.inf)
    k_exit = np.argmin(upper, axis=1)
    t_out = upper[np.arange(len(upper)), k_exit]
    parallel_out = np.any((den == 0) & (num < 0), axis=1)
    t_out = np.where(parallel_out, -np.inf, t_out)
    return t_in, t_out, k_exit


def cast_rays(
    pillow: Pillow,
    cavities: Cavities,
    origins: np.ndarray,
    dirs: np.ndarray,
    candidates: Callable[[int], np.ndarray],
) -> Hits:
    """First solid point along rays ``origins + t·dirs`` (t >= 0).

    origins: (N, 3) µm; dirs: (3,) shared unit direction or (N, 3) unit directions.
    candidates(i): indices of the rays that may pass through cavity i (a superset).
    """
    origins = np.asarray(origins, dtype=np.float64)
    dirs = np.asarray(dirs, dtype=np.float64)
    n_rays = len(origins)
    # Start and stop on the bounding box of the body (slab method).
    half = pillow.bounding_half_um
    d = np.broadcast_to(dirs, origins.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origins) / d
        t2 = (half - origins) / d
    parallel = d == 0
    inside_slab = np.abs(origins) <= half
    lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    t_near, t_far = np.max(lo, axis=1), np.min(hi, axis=1)
    crosses = (t_near <= t_far) & (t_far > 0)
    t = np.where(crosses, np.maximum(t_near, 0.0), np.inf)
    t_far = np.where(crosses, t_far, -np.inf)
    facet = np.full(n_rays, -1)
    exit_normal = np.zeros((n_rays, 3))
    cand = [candidates(i) for i in range(len(cavities))]
    pending = np.ones(n_rays, bool)
    for _ in range(4):
        t_body = _march_body(pillow, origins, dirs, np.where(pending, t, np.inf), t_far)
        t_body = _newton_rough(pillow, origins, dirs, t_body)
        t = np.where(pending, t_body, t)
        facet[pending] = -1
        moved_any = np.zeros(n_rays, bool)
        intervals = []
        for i, idx in enumerate(cand):
            idx = idx[pending[idx] & np.isfinite(t[idx])]
            if idx.size:
                d = dirs if dirs.ndim == 1 else dirs[idx]
                intervals.append((i, idx, *_cavity_intervals(cavities, i, origins[idx], d)))
        for _pass in range(8):
            moved = np.zeros(n_rays, bool)
            for i, idx, t_in, t_out, k_exit in intervals:
                inside = (t_in < t[idx] + 1e-6) & (t[idx] < t_out - 1e-6)
                if not inside.any():
                    continue
                sel = idx[inside]
                t[sel] = t_out[inside]
                facet[sel] = i
                exit_normal[sel] = -cavities.normals[i, k_exit[inside]]
                moved[sel] = True
            moved_any |= moved
            if not moved.any():
                break
        # A facet point must lie in the body; otherwise the ray left the body inside
        # the cavity (grazing) and must be marched again from there.
        check = np.flatnonzero(moved_any & np.isfinite(t))
        d = dirs if dirs.ndim == 1 else dirs[check]
        outside = pillow.sdf(origins[check] + t[check, None] * d) > _HIT_TOL_UM
        pending = np.zeros(n_rays, bool)
        pending[check[outside]] = True
        t[check[outside]] += _HIT_TOL_UM
        if not pending.any():
            break
    t[pending] = np.inf
    hit = np.isfinite(t)
    normals = np.full((n_rays, 3), np.nan)
    body = np.flatnonzero(hit & (facet < 0))
    d = dirs if dirs.ndim == 1 else dirs[body]
    _, grad = pillow.sdf_and_gradient(origins[body] + t[body, None] * d)
    normals[body] = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    # A ray that left a cavity inside the roughness band behind the body can be refined onto
    # the far side, where the surface faces away from it: that is where it leaves the body,
    # never a first hit (rays start outside), so it misses.
    away = body[np.sum(normals[body] * d, axis=1) > 0]
    t[away], hit[away], normals[away] = np.inf, False, np.nan
    on_facet = hit & (facet >= 0)
    normals[on_facet] = exit_normal[on_facet]
    return Hits(t_um=t, hit=hit, normals=normals, facet=np.where(hit, facet, -1))
