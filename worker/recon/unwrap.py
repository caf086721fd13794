"""Temporal (hierarchical) phase unwrapping of object − reference phase differences.

For one azimuth the fringe sets come with periods P_0 > P_1 > … > P_{N−1} (coarse → fine).
Per pixel and period the object−reference difference Δψ_i = −2π·h·tanθ/P_i is known modulo 2π
(the pattern's unknown constant cancels in the difference).  The spec guarantees
|Δψ_0| < π for the coarsest period, so Δψ_0 needs no unwrapping; every coarser unwrapped
phase, scaled by P_{i−1}/P_i, predicts the finer one and fixes its 2π order (Huntley &
Saldner 1993; Zuo et al. 2016, "Temporal phase unwrapping algorithms for fringe projection
profilometry: a comparative review", hierarchical approach).  The order is right while the
scaled prediction error stays below π, i.e. σ_{Δψ,i−1}·P_{i−1}/P_i ≪ π: a ratio of 2 (the
paper's doubling periods) tolerates phase errors up to ±π/2 on the coarser level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "UnwrappedPhase",
    "paper_consistent_unwrap",
    "phase_difference",
    "temporal_unwrap",
    "wrap_phase",
]

_TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class UnwrappedPhase:
    """Output of :func:`temporal_unwrap`.

    dpsi_rad : (H, W) float32, the unwrapped object − reference phase expressed for the
        FINEST period P_{N−1} (a level ℓ's phase is scaled by P_ℓ/P_{N−1}), so that
        h = −dpsi·P_{N−1}/(2π tanθ) whichever level a pixel stopped at.  NaN where the
        coarsest level is unusable or NaN.
    order_residual : (H, W) float32, the largest |prediction − unwrapped| over the levels, in
        fringe orders (cycles): 0 is perfect agreement, 0.5 a coin toss on the order.  A
        reliability map: values above ~0.25 flag pixels whose order may be wrong.
    level_used : (H, W) int16, index of the finest level that refined the pixel (−1: none).
    weight : (H, W) float32, relative inverse variance of the height, (m·P_{N−1}/P_ℓ)² with m
        the modulation at the level used (1 when no modulation was given); 0 where NaN.
    """

    dpsi_rad: np.ndarray
    order_residual: np.ndarray
    level_used: np.ndarray
    weight: np.ndarray


def wrap_phase(phase_rad: np.ndarray, *, cycle_rad: float = _TWO_PI) -> np.ndarray:
    """Wrap to (−cycle/2, cycle/2]; default (−π, π].  Keeps the dtype of float input."""
    x = np.asarray(phase_rad)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    half = cycle_rad / 2.0
    return (x - cycle_rad * np.ceil((x - half) / cycle_rad)).astype(x.dtype, copy=False)


def phase_difference(object_rad: np.ndarray, reference_rad: np.ndarray) -> np.ndarray:
    """Object − reference wrapped phase, wrapped to (−π, π]; same shape as the inputs."""
    obj = np.asarray(object_rad)
    ref = np.asarray(reference_rad)
    if obj.shape != ref.shape:
        raise ValueError(f"reference_rad shape {ref.shape} differs from object_rad {obj.shape}")
    return wrap_phase(obj.astype(np.float32) - ref.astype(np.float32))


def _check(wrapped_rad, period_um):
    w = np.asarray(wrapped_rad)
    if w.ndim != 3 or w.shape[0] < 1:
        raise ValueError(f"wrapped_rad must have shape (N, H, W), got {w.shape}")
    p = np.asarray(period_um, dtype=np.float64)
    if p.shape != (w.shape[0],):
        raise ValueError(f"period_um must have shape ({w.shape[0]},), got {p.shape}")
    if not np.all(np.isfinite(p) & (p > 0)):
        raise ValueError("period_um must be finite and > 0")
    if np.any(np.diff(p) >= 0):
        raise ValueError("period_um must decrease strictly (coarse → fine)")
    return w.astype(np.float32, copy=False), p


def temporal_unwrap(
    wrapped_rad: np.ndarray,
    period_um,
    *,
    modulation: np.ndarray | None = None,
    min_modulation: float = 0.15,
) -> UnwrappedPhase:
    """Hierarchical temporal unwrapping, coarse → fine, stopping where fringes fade.

    Parameters
    ----------
    wrapped_rad : (N, H, W) float
        Object − reference phase differences per period (see :func:`phase_difference`),
        coarsest first; wrapped values in any 2π range (they are re-wrapped).  NaN allowed.
    period_um : (N,) float
        Fringe periods in µm, strictly decreasing.
    modulation : (N, H, W) float, optional
        Fringe modulation B/A per level, best the smaller of object and reference.  A level
        whose modulation is below ``min_modulation`` at a pixel does not refine it: periods
        finer than the camera or the projector resolve (the reference target shows it),
        shadows and blurred walls.  The pixel keeps the scaled phase of its last good level,
        and finer good levels may pick up from there (the scaled prediction error grows with
        the skipped ratio; ``order_residual`` shows it).
    min_modulation : float
        Threshold for ``modulation``.

    Returns
    -------
    UnwrappedPhase
    """
    w, p = _check(wrapped_rad, period_um)
    if modulation is not None:
        mod = np.asarray(modulation, dtype=np.float32)
        if mod.shape != w.shape:
            raise ValueError(f"modulation must have shape {w.shape}, got {mod.shape}")
        good = np.nan_to_num(mod, nan=0.0) >= np.float32(min_modulation)
    else:
        mod = None
        good = np.ones(w.shape, dtype=bool)
    two_pi = np.float32(_TWO_PI)
    phi = np.where(good[0], wrap_phase(w[0]), np.float32(np.nan))
    level = np.where(np.isfinite(phi), 0, -1).astype(np.int16)
    worst = np.zeros(phi.shape, dtype=np.float32)
    for i in range(1, w.shape[0]):
        pred = phi * np.float32(p[i - 1] / p[i])
        # No re-wrap needed: the rounding picks the 2π order whatever range w[i] is in.
        wi = w[i]
        refined = wi + two_pi * np.round((pred - wi) / two_pi)
        use = good[i] & np.isfinite(refined)
        phi = np.where(use, refined, pred)
        worst = np.where(use, np.maximum(worst, np.abs(pred - refined) / two_pi), worst)
        level = np.where(use, np.int16(i), level)
    finite = np.isfinite(phi)
    lev = np.clip(level, 0, None)
    m_used = np.take_along_axis(mod, lev[None], axis=0)[0] if mod is not None else 1.0
    weight = (m_used * np.float32(p[-1]) / p[lev].astype(np.float32)) ** 2
    return UnwrappedPhase(
        dpsi_rad=phi.astype(np.float32),
        order_residual=np.where(finite, worst, np.float32(np.nan)),
        level_used=level,
        weight=np.where(finite, weight, 0.0).astype(np.float32),
    )


def paper_consistent_unwrap(half_range_rad: np.ndarray, period_um) -> UnwrappedPhase:
    """The paper's consistent-phase selection (our reading of Kumar et al. 2003, Eq. 5).

    The Carré formula as written (arctan, not atan2) gives each phase only modulo π.  On the
    paper's schedule the coarsest pattern spans a quarter of a period across the projector,
    so its phase varies by less than π/2 and is taken as is; every finer, doubled period is
    then the candidate ψ_i + kπ closest to the doubled coarser phase.  Here applied to the
    object − reference differences: it needs |Δψ_0| < π/2 and prediction errors below π/2
    (half the margin of :func:`temporal_unwrap`), which is why the full-range estimator and
    2π selection are our default.

    half_range_rad : (N, H, W), differences known modulo π (e.g. of
    ``carre_phase(..., quadrant="paper")``), coarsest first; period_um : (N,) decreasing.
    """
    w, p = _check(half_range_rad, period_um)
    phi = wrap_phase(w[0], cycle_rad=np.pi)
    worst = np.zeros(phi.shape, dtype=np.float32)
    for i in range(1, w.shape[0]):
        pred = phi * np.float32(p[i - 1] / p[i])
        order = np.round((pred - w[i]) / np.float32(np.pi))
        phi = w[i] + np.float32(np.pi) * order
        worst = np.maximum(worst, np.abs(pred - phi) / np.float32(_TWO_PI))
    finite = np.isfinite(phi)
    return UnwrappedPhase(
        dpsi_rad=phi.astype(np.float32),
        order_residual=np.where(finite, worst, np.float32(np.nan)),
        level_used=np.where(finite, w.shape[0] - 1, -1).astype(np.int16),
        weight=finite.astype(np.float32),
    )
