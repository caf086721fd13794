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

from worker.recon.arrays import copy_where
from worker.recon.parallel import run_blocks

__all__ = [
    "UnwrappedPhase",
    "noise_aware_unwrap",
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
        reliability map: values above ~0.25 flag pixels whose order may be wrong.  None from
        :func:`noise_aware_unwrap` with ``diagnostics=False``.
    level_used : (H, W) int16, index of the finest level that refined the pixel (−1: none).
    weight : (H, W) float32, relative inverse variance of the height, (m·P_{N−1}/P_ℓ)² with m
        the modulation at the level used (1 when no modulation was given); 0 where NaN.
        From :func:`noise_aware_unwrap`: the absolute inverse variance 1/σ² (rad⁻²); None
        with ``diagnostics=False``.
    sigma_rad : (H, W) float32 or None, standard deviation of ``dpsi_rad`` predicted from the
        phase noise (:func:`noise_aware_unwrap` only); NaN where ``dpsi_rad`` is.
    conflicts : (H, W) int16 or None, number of levels whose fringe was detected but that
        were not accepted (ambiguous order or residual beyond the noise: a corrupt level, or
        a wrong order earlier on); :func:`noise_aware_unwrap` only.
    """

    dpsi_rad: np.ndarray
    order_residual: np.ndarray | None
    level_used: np.ndarray
    weight: np.ndarray | None
    sigma_rad: np.ndarray | None = None
    conflicts: np.ndarray | None = None


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


def noise_aware_unwrap(
    wrapped_rad: np.ndarray,
    sigma_rad: np.ndarray,
    period_um,
    *,
    max_ambiguity: float = 1e-3,
    k_sigma: float = 4.0,
    model_sigma_rad: float = 0.03,
    workers: int = 1,
    diagnostics: bool = True,
) -> UnwrappedPhase:
    """Temporal unwrapping that fixes an order only where the noise makes it unambiguous.

    Every level i measures the finest-period phase Φ through φ_i ≡ q_i·Φ + n_i (mod 2π), with
    q_i = P_{N−1}/P_i and n_i ~ N(0, σ_i²) (σ_i of the object − reference difference, e.g.
    √(σ_obj² + σ_ref²) from :func:`worker.recon.fringe.phase_sigma_rad`).  Coarse → fine, the
    least-squares estimate Φ̂ of all accepted levels (variance 1/Σ q_j²/σ_j²) predicts
    q_i·Φ̂; the nearest order gives the residual r (|r| ≤ π), whose variance under the right
    order is s² = q_i²·var(Φ̂) + σ_i².  The level is accepted when

    * the runner-up order (r ∓ 2π) is at most ``max_ambiguity`` as likely, i.e.
      (2π − |r|)² − r² ≥ 2·s²·ln(1/max_ambiguity), equivalently |r| ≤ π − s²·ln(1/ε)/(2π);
    * r itself is consistent with the noise, |r| ≤ ``k_sigma``·s.

    A rejected level is skipped, not fatal: a finer level may still be fixed from the coarser
    estimate (the test accounts for the larger ratio).  This is the sequential form of the
    multi-frequency maximum-likelihood order choice (Zuo et al. 2016, the noise analysis of
    hierarchical and multi-frequency unwrapping): each accepted level's order is the maximum-likelihood one given all coarser accepted levels,
    and the final Φ̂ is their joint least-squares estimate, not the finest level alone.  The
    coarsest level is unambiguous by the spec (|Δψ_0| < π); it is accepted when it is at least
    ``sqrt(2 ln(1/ε))``·σ_0 from ±π and precise enough to fix the next level's order.  A pixel
    whose coarsest level fails is NaN (no absolute order for it at this azimuth).

    Each level's variance is σ_i² + ``model_sigma_rad``² for the tests and the weights (not
    for the detection): the phase error no noise figure shows — the pattern's harmonics, the
    pixel's area, blur on slopes — so that nearly noise-free data do not call their own
    model errors inconsistent.

    A detected level that either test rejects is a *conflict*: that level is corrupt
    (interreflection, highlight), or an earlier order was wrong, in which case the following
    levels conflict as well (the least-squares estimate, pulled by the right coarser levels,
    no longer predicts them).  Callers should drop pixels whose conflicts persist.

    Parameters
    ----------
    wrapped_rad : (N, H, W) float, object − reference differences, coarsest first.
    sigma_rad : (N, H, W) float, their standard deviations (inf or NaN: level unusable).
    period_um : (N,) strictly decreasing.
    workers : threads sharing the blocks of rows (the result does not depend on it).
    diagnostics : False leaves ``order_residual`` and ``weight`` out (None), for callers that
        only use the estimate, its σ, the levels and the conflicts.
    """
    w, p = _check(wrapped_rad, period_um)
    sig = np.asarray(sigma_rad, dtype=np.float32)
    if sig.shape != w.shape:
        raise ValueError(f"sigma_rad must have shape {w.shape}, got {sig.shape}")
    if not 0.0 < max_ambiguity < 1.0:
        raise ValueError(f"max_ambiguity must lie in (0, 1), got {max_ambiguity}")
    if not k_sigma > 0:
        raise ValueError(f"k_sigma must be > 0, got {k_sigma}")
    log_eps = np.float32(np.log(1.0 / max_ambiguity))
    z = np.float32(np.sqrt(2.0 * log_eps))
    k2 = np.float32(k_sigma * k_sigma)
    q = (p[-1] / p).astype(np.float32)

    n_lev = w.shape[0]
    rows = w.shape[1]
    shape = w.shape[1:]
    out = {
        name: np.empty(shape, dtype=dtype)
        for name, dtype in (
            ("est", np.float32),
            ("worst", np.float32),
            ("info", np.float32),
            ("sigma", np.float32),
            ("level", np.int16),
            ("conflicts", np.int16),
        )
        if diagnostics or name not in ("worst", "info")
    }
    # Blocks of rows small enough for the CPU cache: the level loop makes ~30 passes over
    # each, which on whole megapixel images would be bound by memory bandwidth.
    step = max(1, 32768 // max(1, int(np.prod(shape[1:], dtype=np.int64))))
    consts = (q, np.float32(p[0] / p[1]) if n_lev > 1 else None, z, log_eps, k2, model_sigma_rad)
    nan_rows = np.full((step, *shape[1:]), np.nan, np.float32)

    def unwrap_rows(r0: int) -> None:
        sl = slice(r0, min(rows, r0 + step))
        est, info, worst, level, conf = _unwrap_block(
            w[:, sl], sig[:, sl], *consts, diagnostics=diagnostics
        )
        # The outputs' NaN and 0 where the estimate is not, in the block still in cache.
        undefined = ~(np.isfinite(est) & (info > 0))
        with np.errstate(divide="ignore"):
            sigma = np.sqrt(info, out=out["sigma"][sl])
            np.divide(np.float32(1.0), sigma, out=sigma)
        nan = nan_rows[: len(est)]
        copy_where(sigma, nan, undefined)
        copy_where(est, nan, undefined)
        out["est"][sl] = est
        if diagnostics:
            copy_where(worst, nan, undefined)
            out["worst"][sl] = worst
            info *= ~undefined  # np.where(…, info, 0): info is finite (σ ≥ 1e-5 rad)
            out["info"][sl] = info
        out["level"][sl], out["conflicts"][sl] = level, conf

    # Pixels are independent: the blocks may run in threads.
    run_blocks(unwrap_rows, range(0, rows, step), workers=workers)
    return UnwrappedPhase(
        dpsi_rad=out["est"],
        order_residual=out.get("worst"),
        level_used=out["level"],
        weight=out.get("info"),
        sigma_rad=out["sigma"],
        conflicts=out["conflicts"],
    )


def _unwrap_block(w, sig, q, ratio01, z, log_eps, k2, model_sigma_rad, *, diagnostics=True):
    """:func:`noise_aware_unwrap` on a block of rows; returns est, info, worst (None without
    diagnostics), level, conflicts."""
    two_pi = np.float32(_TWO_PI)
    pi = np.float32(np.pi)
    amb = log_eps / two_pi
    one = np.float32(1.0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        # Fringe detection: for pure noise B²/σ_I² is Exp(1)-distributed (the two 4-step
        # quadratures are N(0, 2σ_I²)), so σ_ψ = σ_I/(√2·B) ≤ 1/z has false-alarm rate ε:
        # a shadowed pixel whose noise happens to look like a fringe fixes no order.
        # σ = 0 (noise-free synthetic frames) would make every estimate ∞/∞: floor it at
        # 1e-5 rad, well above float32 phase rounding and below any camera's noise.
        # σ = 0 (noise-free synthetic frames) must still count as detected.
        # The floor as a row that broadcasts: np.maximum against a scalar runs ~2× slower.
        var = np.maximum(sig, np.full(sig.shape[-1], np.float32(1e-5)))
        var *= var
        detected = var * (z * z) <= one
        # The model error no noise figure shows (pattern harmonics, pixel integration, blur
        # on slopes) bounds every level's precision: without it, nearly noise-free data
        # would call their own model errors inconsistent.
        var += np.float32(model_sigma_rad**2)
        inv_var = np.zeros_like(var)
        copy_where(inv_var, one / var, detected)
        u0 = wrap_phase(w[0])
        ok = (pi - np.abs(u0)) * np.sqrt(inv_var[0]) >= z
        if ratio01 is not None:
            # Useful only if it can fix the next level: its scaled error must stay unambiguous.
            ok &= inv_var[0] * np.square(pi / (z * ratio01)) > one
        info = np.where(ok, inv_var[0] * (q[0] * q[0]), np.float32(0))
        num = np.where(ok, inv_var[0] * (q[0] * u0), np.float32(0))
        est = np.where(ok, u0 / q[0], np.float32(np.nan))
        level = np.where(ok, 0, -1).astype(np.int16)
        # Largest accepted |r| in rad, turned into cycles at the end (the division by 2π is
        # monotonic: the same float32 maximum as dividing every level's r).
        worst = np.zeros(u0.shape, dtype=np.float32) if diagnostics else None
        accepted = np.zeros(u0.shape, dtype=np.int16)
        for i in range(1, w.shape[0]):
            qi = q[i]
            # float32 rounding of the prediction: |Φ| < π·P_0/P_{N−1} by the spec.
            eps2 = np.float32((1e-6 * np.pi * qi / q[0]) ** 2)
            pred = est * qi
            u = pred - w[i]
            u /= two_pi
            np.rint(u, out=u)
            u *= two_pi
            u += w[i]
            r = np.subtract(u, pred, out=pred)
            np.abs(r, out=r)
            var = (qi * qi) / info
            var += one / inv_var[i]
            var += eps2
            acc = r <= pi - var * amb
            acc &= np.square(r) <= k2 * var
            # A level accepted has been detected (undetected: 1/inv_var = ∞ fails the
            # test), so the conflicts are the detected levels less the accepted ones.
            accepted += acc
            # × acc: np.where(acc, inv_var[i], 0) as inv_var is finite and ≥ 0.
            inv = inv_var[i] * acc
            info += inv * (qi * qi)
            inv *= qi
            inv *= u
            num += inv
            copy_where(est, num / info, acc)
            if diagnostics:
                copy_where(worst, np.maximum(worst, r, out=r), acc)
            copy_where(level, np.full_like(level, i), acc)
        if diagnostics:
            worst /= two_pi
        conflicts = detected[1:].sum(axis=0, dtype=np.int16)
        conflicts -= accepted
    return est, info, worst, level, conflicts


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
