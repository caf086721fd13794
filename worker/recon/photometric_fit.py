"""Robust per-pixel Lambertian least squares, vectorised: the machinery behind
:func:`worker.recon.photometric.photometric_stereo`.

Arrays are (K, n): K lights, n pixels of one chunk.  b = ρ·n per pixel from the 3×3 normal
equations solved by cofactors; the inlier set of each pixel is chosen by consensus with
asymmetric scoring (highlights lie above the Lambertian fit, shadows below), trimmed on
studentised residuals and re-admitted until it settles.  See docs/reconstruction.md, stage 2.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = [
    "Model",
    "cone_resolve",
    "coherent_normals",
    "consensus_light_sets",
    "consensus_refit",
    "consistent_least_squares",
    "estimate_sigma",
    "initial_inliers",
    "mirror_trim",
    "robust_fit",
]

# Half-angle cones (between normal and half vector) of the mirror-exclusion hypotheses; the
# wide one only with dense light sets (see _hypotheses).
_MIRROR_CONES_DEG = (15.0, 30.0)
_DENSE_LIGHTS = 32


def _count(mask: np.ndarray) -> np.ndarray:
    """Per pixel, the number of True samples of a (K, n) bool array, int64 as ``sum(axis=0)``.

    Summed as bytes (a bool sum casts every element to int64 first; this is ~8× faster,
    and the photometric fit counts inliers some thousand times per scan).
    """
    if mask.shape[0] >= 256:
        return mask.sum(axis=0)
    return mask.view(np.uint8).sum(axis=0, dtype=np.uint8).astype(np.int64)


def _at_least(x: np.ndarray, lo, out: np.ndarray | None = None) -> np.ndarray:
    """``np.maximum(x, lo)`` for a float32 array and a scalar, against a row of ``lo`` that
    broadcasts: the same values ~3× faster (numpy's maximum against a scalar operand takes
    a slower loop than two arrays strided alike)."""
    return np.maximum(x, np.full(x.shape[-1], lo, dtype=x.dtype), out=out)


def _cols(x: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Columns ``sel`` (int indices or a bool mask) of a (K, n) array, as a C-ordered copy.

    np.take / np.compress gather 2–3× faster than ``x[:, sel]``, whose copy also comes out
    F-ordered, so that every later (K, n) pass over it walks across the rows.
    """
    if sel.dtype == bool:
        return np.compress(sel, x, axis=1)
    return np.take(x, sel, axis=1)


def _rows(x: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Rows ``sel`` (int indices or a bool mask) of a per-pixel (n,) or (n, 3) array: as
    :func:`_cols`, np.take / np.compress gather several times faster than ``x[sel]``."""
    if sel.dtype == bool:
        return np.compress(sel, x, axis=0)
    return np.take(x, sel, axis=0)


def _set_cols(x: np.ndarray, cols: np.ndarray, values: np.ndarray) -> None:
    """``x[:, cols] = values`` for a C-ordered (K, n) x, by flat indices (twice as fast)."""
    if not x.flags.c_contiguous:
        raise ValueError("_set_cols needs a C-ordered array")
    flat = (np.arange(x.shape[0])[:, None] * x.shape[1] + cols).ravel()
    x.reshape(-1)[flat] = values.reshape(-1)


def _select(mask: np.ndarray, a: np.ndarray, b=0) -> np.ndarray:
    """``np.where(mask, a, b)`` bit for bit, for a bool or float32 array ``a`` and ``b`` an
    array of its dtype or a scalar, by bit masks: np.where branches per element, which on a
    mixed mask runs ~10× slower than one arithmetic pass."""
    bits = np.int8 if a.dtype == bool else np.int32
    if a.dtype not in (np.dtype(bool), np.dtype(np.float32)):
        raise TypeError(f"_select takes bool or float32 arrays, not {a.dtype}")
    on = np.negative(mask.view(np.int8))  # every bit set where mask is True
    out = np.bitwise_and(a.view(bits), on, dtype=bits)
    b_bits = np.asarray(b, a.dtype).view(bits)
    if b_bits.ndim or b_bits != 0:
        out |= np.bitwise_and(np.bitwise_not(on), b_bits, dtype=bits)
    return out.view(a.dtype)


def _solve_sym3(m6: np.ndarray, rhs: np.ndarray, min_condition: float):
    """Solve M x = rhs for batched symmetric 3×3 M given as (6, N) rows (a, b, c, d, e, f).

    M = [[a, b, c], [b, d, e], [c, e, f]], by cofactors (exact, vectorised, no (N, 3, 3)
    temporaries); rhs (3, N).  Returns x (N, 3) float64 and a bool mask of the systems whose
    normalised determinant det/(trace/3)^3 exceeds ``min_condition``.
    """
    cof, ok = _inverse_sym3(m6, min_condition)
    i11, i12, i13, i22, i23, i33 = cof
    r0, r1, r2 = np.ascontiguousarray(rhs, dtype=np.float64)
    x = np.empty((m6.shape[1], 3))
    x[:, 0] = i11 * r0 + i12 * r1 + i13 * r2
    x[:, 1] = i12 * r0 + i22 * r1 + i23 * r2
    x[:, 2] = i13 * r0 + i23 * r1 + i33 * r2
    return x, ok


def _inverse_sym3(m6: np.ndarray, min_condition: float):
    """M⁻¹ of batched symmetric 3×3 M, (6, N) as in :func:`_solve_sym3`, by cofactors:
    returns it as (6, N) float64 (0 where not ok) and the conditioning mask ``ok``."""
    # Rows of a (6, N) array: every term below is a contiguous pass.
    a, b, c, d, e, f = np.ascontiguousarray(m6, dtype=np.float64)
    n = m6.shape[1]
    cof, tmp = np.empty((6, n)), np.empty(n)
    # Each cofactor p·q − r·s with the products rounded as written, into its row.
    for row, (p, q, r, s) in enumerate(
        ((d, f, e, e), (c, e, b, f), (b, e, c, d), (a, f, c, c), (b, c, a, e), (a, d, b, b))
    ):
        np.multiply(p, q, out=cof[row])
        cof[row] -= np.multiply(r, s, out=tmp)
    det = a * cof[0]
    det += np.multiply(b, cof[1], out=tmp)
    det += np.multiply(c, cof[2], out=tmp)
    tr = np.add(a, d, out=tmp)
    tr += f
    tr /= 3.0
    ok = det > min_condition * tr**3
    # 1/det only where ok (det > 0 there): no division by zero to silence.
    cof *= np.divide(1.0, det, out=np.zeros(n), where=ok)
    return cof, ok


def _fit(s, weight, lights32, ll6):
    """Weighted least-squares b per pixel; s, weight (K, N), weight 0 leaves a sample out."""
    w = weight.astype(np.float32, copy=False)
    # (6, K) @ (K, N): the normal equations come out as C-ordered rows, which _solve_sym3
    # reads in contiguous passes (bit for bit the transpose of (N, K) @ (K, 6)).
    m6 = ll6.T @ w
    rhs = lights32.T @ (w * s)
    enough = _count(weight if weight.dtype == bool else weight > 0) >= 3
    b, ok = _solve_sym3(m6, rhs, 1e-3)
    ok &= enough
    return b, ok


def _leverage(inliers, ll6):
    """h (K, N) = l_kᵀ M⁻¹ l_k, M = Σ l lᵀ over each pixel's ``inliers`` (K, N) bool: the
    hat-matrix diagonal of the unit-weight fit, for deleted residuals r/(1 − h); 0 where M
    is ill-conditioned.  Only M is needed, not the fit (the trims called _fit for it)."""
    cof, _ = _inverse_sym3(ll6.T @ inliers.astype(np.float32), 1e-3)
    # Off-diagonal terms of lᵀ M⁻¹ l appear twice.
    ll6d = ll6 * np.array([1, 2, 2, 1, 2, 1], dtype=np.float32)
    # (K, 6) @ (6, N): h comes out C-ordered (K, N) like the residuals it scales.
    return ll6d @ cof.astype(np.float32)


def _sorted_per_pixel(x: np.ndarray) -> np.ndarray:
    """Each pixel's K samples in ascending order, (n, K): sorting contiguous rows is twice as
    fast as sorting the (K, n) array along its strided first axis."""
    rows = np.ascontiguousarray(x.T)
    rows.sort(axis=1)
    return rows


def initial_inliers(s: np.ndarray, valid: np.ndarray, shadow_fraction: float, floor=0.0):
    """Rank-based candidates: drop shadows and gross highlights (relative to upper quartile).

    ``floor`` (a few σ of the noise) is the least a lit sample can read, and the quartile is
    taken over the samples above it: where most lights are shadowed the upper quartile of
    all samples is itself a shadow, and thresholds relative to it would take noise for
    signal and cut every lit sample as a "highlight".
    """
    k = s.shape[0]
    lit = valid & (s > np.float32(floor))
    ranked = _sorted_per_pixel(np.where(lit, s, -np.inf))
    # The upper quartile of the lit samples ignores up to a quarter of specular spikes.
    idx = np.clip(k - 1 - _count(lit) // 4, 0, k - 1)
    level = ranked[np.arange(ranked.shape[0]), idx]
    level = np.where(np.isfinite(level), level, 0.0).astype(np.float32)
    # Only gross highlights are cut here: when many lights are shadowed the upper quartile
    # can be a grazing sample well below the lit ones.  The robust fit copes with the rest.
    return lit & (s > shadow_fraction * level) & (s < 4.0 * level), level


def _l1_start(s, cand, lights32, ll6, delta, iterations=6):
    """Least absolute deviations over the candidates by IRLS (weights 1/max(|r|, delta))."""
    b, ok = _fit(s, cand, lights32, ll6)
    for _ in range(iterations):
        r = np.abs(s - lights32 @ b.astype(np.float32).T)
        w = _select(cand, 1.0 / _at_least(r, np.float32(delta), out=r))
        w /= np.maximum(w.max(axis=0, keepdims=True), np.float32(1e-30))
        b_new, ok_new = _fit(s, w, lights32, ll6)
        b = np.where(ok_new[:, None], b_new, b)
        ok |= ok_new
    return b, ok


def _lower_start(s, cand, lights32, ll6, delta, tau=0.25, iterations=8):
    """Regression quantile τ over the candidates by IRLS (Koenker & Bassett 1978).

    Weights τ/|r| above the fit and (1 − τ)/|r| below it: the fit settles where a fraction τ
    of the samples lies below it, near the lower envelope of the data.  Lambertian shading is
    that envelope when highlights and interreflections (which only add light) cover most of
    the lights, as with a glossy or dark surface under a dense light set; LS and L1 starts are
    then pulled up toward the lobe.
    """
    b, ok = _fit(s, cand, lights32, ll6)
    above, below = np.float32(tau), np.float32(1.0 - tau)
    for _ in range(iterations):
        r = s - lights32 @ b.astype(np.float32).T
        w = np.where(r > 0, above, below) / _at_least(np.abs(r), np.float32(delta))
        w = _select(cand, w)
        w /= np.maximum(w.max(axis=0, keepdims=True), np.float32(1e-30))
        b_new, ok_new = _fit(s, w, lights32, ll6)
        b = np.where(ok_new[:, None], b_new, b)
        ok |= ok_new
    return b, ok


class Model:
    """Per-chunk constants and the tolerance model shared by the robust-fit steps."""

    def __init__(self, s, valid, lights32, ll6, shadow_fraction, tolerance, abs_tol, half32=None):
        self.s, self.valid, self.lights32, self.ll6 = s, valid, lights32, ll6
        # Half vectors of the lights with the view direction (None: no mirror hypotheses).
        self.half32 = half32
        self.shadow = np.float32(shadow_fraction)
        self.tolerance = np.float32(tolerance)
        self.abs_tol = np.float32(abs_tol)

    def sub(self, cols):
        """The same model restricted to the pixels ``cols``."""
        return Model(
            _cols(self.s, cols),
            _cols(self.valid, cols),
            self.lights32,
            self.ll6,
            self.shadow,
            self.tolerance,
            self.abs_tol,
            self.half32,
        )

    def residual(self, b, cols=slice(None)):
        """Signed residual s − l·b, the tolerance and the terminator test, each (K, n)."""
        b32 = b.astype(np.float32)
        pred = self.lights32 @ b32.T
        rho = np.sqrt(np.einsum("ni,ni->n", b32, b32))
        front = pred > self.shadow * rho
        # In place: these (K, n) passes dominate the cost of the whole fit.
        r = np.subtract(self.s if isinstance(cols, slice) else _cols(self.s, cols), pred)
        tol = _at_least(pred, np.float32(0.0), out=pred)
        tol *= self.tolerance
        tol += max(self.abs_tol, np.float32(1e-12))
        return r, tol, front

    def select(self, b):
        r, tol, front = self.residual(b)
        inl = np.less_equal(np.abs(r, out=r), tol)
        inl &= front
        inl &= self.valid
        return inl

    def score(self, b, ok, cand):
        """Consensus count, minus candidates far below the fit or lit behind its terminator,
        minus a tie-breaking misfit.

        Samples above the shadow threshold that sit far BELOW a fit are implausible (only a
        penumbra does that), whereas highlights and interreflections sit above it: a fit
        through highlights leaves good samples below it and is penalised.
        """
        r, tol, front = self.residual(b)
        inl = self.valid & front & (np.abs(r) <= tol)
        # A clearly lit candidate that the fit puts behind the terminator is as implausible:
        # attached shadow would leave it dark.  (With four lights an exact fit through a
        # highlight that banishes a good sample there otherwise ties with the right one.)
        below = cand & ((r < -tol) | (~front & (r > tol)))
        m = _count(inl)
        misfit = _select(inl, (r / tol) ** 2).sum(axis=0) / np.maximum(m, 1)
        return np.where(ok, m - _count(below) - 0.01 * misfit, -np.inf)

    def trim(self, inl, b, ok, ratio=None):
        """Backward elimination on studentised residuals r/sqrt(1 − h), one sample per round.

        Removing one sample at a time, judged by the residual it would have if left out of
        the fit, catches high-leverage highlights that hide from the raw residuals.
        ``ratio``: |r|/tol of every sample for the fit b, when the caller has it.
        """
        inl = inl.copy()
        b, ok = b.copy(), ok.copy()
        cols = None  # the first round looks at every pixel without gathering columns
        # Few rounds: the batch removal below empties most pixels in one or two, and what a
        # round cap leaves is caught by the tolerance test of the next selection.
        for _ in range(min(self.s.shape[0] - 3, 6)):
            if cols is None:
                if ratio is None:
                    r, tol, _ = self.residual(b)
                    ratio = np.divide(np.abs(r, out=r), tol, out=r)
                raw = _select(inl, ratio)
                many = _count(inl) > 3
            else:
                if cols.size == 0:
                    break
                sub = _cols(inl, cols)
                r, tol, _ = self.residual(_rows(b, cols), cols)
                raw = _select(sub, np.abs(r) / tol)
                many = True
            # Leverage rarely exceeds 0.9 with four or more lights, so a sample whose raw
            # ratio is below 0.3 cannot be the worst misfit: skip those pixels cheaply.
            near = np.flatnonzero((raw.max(axis=0) > 0.3) & many)
            cols = near if cols is None else cols[near]
            sub, raw = _cols(inl, cols), _cols(raw, near)
            if cols.size == 0:
                break
            lev = _leverage(sub, self.ll6)
            # Externally studentised: the deleted residual r/(1 − h) has variance
            # σ²/(1 − h), so r/sqrt(1 − h) is compared with the tolerance.
            ratio = np.subtract(np.float32(1.0), lev, out=lev)
            _at_least(ratio, np.float32(1e-3), out=ratio)
            ratio = np.divide(raw, np.sqrt(ratio, out=ratio), out=ratio)
            n_in = _count(sub)
            worst = ratio.max(axis=0)
            bad = np.flatnonzero((worst > 1.0) & (n_in > 3))
            cols, sub, ratio, n_in, worst = (
                cols[bad],
                _cols(sub, bad),
                _cols(ratio, bad),
                n_in[bad],
                worst[bad],
            )
            if cols.size == 0:
                break
            # The worst sample goes; with many lights, so do up to a quarter of the inliers
            # that misfit at least half as badly (a broad highlight covers many lights and
            # would otherwise cost one round each).  Re-admission restores any good one.
            cap = np.maximum(1, np.minimum(n_in // 4, n_in - 3))
            ranked = -np.sort(-ratio, axis=0)
            cap_thr = np.take_along_axis(ranked, (cap - 1)[None, :], axis=0)[0]
            thr = np.maximum(np.maximum(np.float32(1.0), 0.5 * worst), cap_thr)
            drop = sub & (ratio >= thr[None, :])
            sub &= ~drop
            b_new, ok_new = _fit(_cols(self.s, cols), sub, self.lights32, self.ll6)
            # A removal that leaves lights not spanning 3-D is undone and ends that pixel.
            kept = np.flatnonzero(ok_new)
            cols = cols[kept]
            _set_cols(inl, cols, _cols(sub, kept))
            b[cols], ok[cols] = _rows(b_new, kept), True
        return inl, b, ok


def _hypotheses(model, cand, delta):
    """Alternative starts: L1 over all candidates; LS without the brightest one or two
    (a specular lobe covers one or two neighbouring lights) or without the darkest."""
    s = model.s
    k, n = s.shape
    cols = np.arange(n)
    ranked = np.argsort(np.where(cand, s, -np.inf), axis=0)
    n_cand = _count(cand)
    drops = (
        [ranked[k - 1]],
        [ranked[k - 1], ranked[k - 2]],
        [ranked[np.clip(k - n_cand, 0, k - 1), cols]],
    )
    yield _l1_start(s, cand, model.lights32, model.ll6, delta)
    b_low, ok_low = _lower_start(s, cand, model.lights32, model.ll6, delta)
    yield b_low, ok_low
    if model.half32 is not None:
        # Without the lights whose mirror direction lies near the lower-envelope normal:
        # where a lobe spreads over whole rings of lights no rank-based start escapes it.
        n_low = b_low / np.maximum(np.linalg.norm(b_low, axis=1, keepdims=True), 1e-30)
        cos_h = model.half32 @ n_low.astype(np.float32).T
        # With few lights a 30° cone takes a large share of the bright ones away, and an
        # additive term common to all lights (stray light, interreflections) then flattens
        # the fit: on the simulated hard scan (16 lights) wedge walls by 0.1° on average.
        cones = _MIRROR_CONES_DEG if k >= _DENSE_LIGHTS else _MIRROR_CONES_DEG[:1]
        for cone_deg in cones:
            yield _fit(
                s,
                cand & (cos_h < np.float32(np.cos(np.radians(cone_deg)))),
                model.lights32,
                model.ll6,
            )
    for drop in drops:
        c = cand.copy()
        for d in drop:
            c[d, cols] = False
        yield _fit(s, c, model.lights32, model.ll6)


def _settle(model, cand, b0, ok0):
    """From a start b0: select the consistent samples, refit where they changed, trim."""
    r, tol, front = model.residual(b0)
    ratio = np.abs(r, out=r)
    inl = np.less_equal(ratio, tol)
    inl &= front
    inl &= model.valid
    inl = _select((_count(inl) >= 3)[None, :], inl, cand)
    # |r|/tol of the start, handed to the trim for the pixels whose fit stays b0.
    ratio /= tol
    b, ok = b0.copy(), ok0.copy()
    moved = np.flatnonzero(np.any(inl != cand, axis=0) | ~ok)
    if moved.size:
        b[moved], ok[moved] = _fit(
            _cols(model.s, moved), _cols(inl, moved), model.lights32, model.ll6
        )
        r, tol, _ = model.residual(_rows(b, moved), moved)
        _set_cols(ratio, moved, np.abs(r) / tol)
    return model.trim(inl, b, ok, ratio)


def robust_fit(model, cand, iterations):
    """LS start → select → trim; where that rejects anything, also try the alternative starts
    and keep the best by score; then re-admission rounds until the sets settle.

    Pixels whose candidates in front of the terminator all agree with their least-squares
    fit (most of a clean scan) leave after the first pass, so the costly alternatives run on
    the few that need them.
    """
    b0, ok0 = _fit(model.s, cand, model.lights32, model.ll6)
    inl, b, ok = _settle(model, cand, b0, ok0)
    # Candidates left out only for lying beyond the terminator are not outliers, unless
    # they are clearly lit there; a pixel needs the alternatives when such a sample misfits.
    r, tol, front = model.residual(b)
    misfit = cand & ~inl & (front | (r > tol))
    cols = np.flatnonzero(~ok | np.any(misfit, axis=0))
    if cols.size:
        sub = model.sub(cols)
        sub_cand = _cols(cand, cols)
        best_inl, best_b, best_ok = _cols(inl, cols), _rows(b, cols), ok[cols]
        best_sc = sub.score(best_b, best_ok, sub_cand)
        for h_b, h_ok in _hypotheses(sub, sub_cand, max(float(model.abs_tol), 1e-4)):
            h_inl, h_b, h_ok = _settle(sub, sub_cand, h_b, h_ok)
            sc = sub.score(h_b, h_ok, sub_cand)
            better = sc > best_sc
            best_b = np.where(better[:, None], h_b, best_b)
            best_ok = np.where(better, h_ok, best_ok)
            best_inl = _select(better[None, :], h_inl, best_inl)
            best_sc = np.where(better, sc, best_sc)
        _set_cols(inl, cols, best_inl)
        b[cols], ok[cols] = best_b, best_ok

    # Only pixels whose fit changed after their last selection can re-admit samples.
    for _ in range(iterations):
        if cols.size == 0:
            break
        sub = model.sub(cols)
        new = sub.select(_rows(b, cols))
        old = _cols(inl, cols)
        # Re-admission never drops a pixel below three lights.
        new = _select((_count(new) >= 3)[None, :], new, old)
        moved = np.flatnonzero(np.any(new != old, axis=0))
        cols, new = cols[moved], _cols(new, moved)
        if cols.size == 0:
            break
        sub = model.sub(cols)
        b_new, ok_new = _fit(sub.s, new, sub.lights32, sub.ll6)
        new, b_new, ok_new = sub.trim(new, b_new, ok_new)
        # Keep the previous solution where the new set does not span 3-D.
        take = np.flatnonzero(ok_new | ~ok[cols])
        cols, new, b_new, ok_new = cols[take], _cols(new, take), _rows(b_new, take), ok_new[take]
        _set_cols(inl, cols, new)
        b[cols], ok[cols] = b_new, ok_new
    return b, ok, inl


def estimate_sigma(s, valid, lights32, ll6, shadow_fraction, tolerance):
    """Robust global σ of the Lambertian residual from an evenly strided pixel sample.

    The sample is fitted robustly with the relative tolerance alone; σ is the scaled MAD of
    the residuals of the samples it keeps.
    """
    cand, _ = initial_inliers(s, valid, shadow_fraction)
    model = Model(s, valid, lights32, ll6, shadow_fraction, tolerance, 0.0)
    b, ok, inl = robust_fit(model, cand, 3)
    keep = inl & ok[None, :]
    if not keep.any():
        return 0.0
    resid = np.abs(s - lights32 @ b.astype(np.float32).T)[keep]
    dof = float(np.mean(_count(keep)[ok]))
    # MAD of residuals of a 3-parameter fit from m samples under-reads σ by sqrt((m-3)/m).
    return float(1.4826 * np.median(resid) * np.sqrt(dof / max(dof - 3.0, 1.0)))


def asymmetric_refine(model, inl, b, ok, sigma, iterations=1):
    """Down-weight inliers far ABOVE the fit: a broad glossy lobe adds light to several
    lights within the tolerance, and Lambertian shading is the lower envelope of the data.

    IRLS with w = 1 for r ≤ 2σ and (2σ/r)² above; samples below the fit keep full weight.
    Only pixels with such a sample are refitted.
    """
    if not sigma > 0:
        return b  # no noise scale to judge "far above" by
    two_sigma = np.float32(2.0 * sigma)
    b = b.copy()
    cols = np.arange(model.s.shape[1])
    for _ in range(iterations):
        # The first round looks at every pixel: no gathered copy of the chunk.
        every = cols.size == model.s.shape[1]
        sub = model if every else model.sub(cols)
        # The signed residual alone (Model.residual's tolerance and terminator passes are
        # not needed here).
        r = np.subtract(sub.s, sub.lights32 @ (b if every else _rows(b, cols)).astype(np.float32).T)
        high = (inl if every else _cols(inl, cols)) & (r > two_sigma)
        keep = np.flatnonzero(np.any(high, axis=0) & ok[cols])
        cols, r, high = cols[keep], _cols(r, keep), _cols(high, keep)
        if cols.size == 0:
            break
        w = _select(high, (two_sigma / np.maximum(r, two_sigma)) ** 2, 1.0)
        w = _select(_cols(inl, cols), w)
        b_new, ok_new = _fit(_cols(model.s, cols), w, model.lights32, model.ll6)
        b[cols[ok_new]] = b_new[ok_new]
    return b


def mirror_trim(model, inl, b, ok, sigma, *, rounds=12, k_sigma=2.5, max_cone_deg=45.0):
    """Drop highlight samples in order of their closeness to the mirror direction.

    A specular lobe (Blinn–Phong (n·ĥ)^α, Torrance–Sparrow) peaks at the light whose half
    vector ĥ_k = (l_k + v)/|l_k + v| is nearest the normal and only adds light; its tail
    passes any relative tolerance yet biases the normal.  Each round looks at the inlier
    nearest the mirror direction of the current fit and drops it when its deleted residual
    is significantly positive: r/sqrt(1 − h) > k_sigma·σ (externally studentised, h the
    leverage).  Its next-nearest neighbour is judged in the next round, so a lobe is
    peeled from the top until what remains nearest the mirror direction fits to noise,
    whatever the exponent, the number of lights and their polar angles.  σ is one global
    figure: under shot noise the bright nearest-mirror sample is noisier than that, and a
    Lambertian pixel loses it to noise with probability ~1 % (more than the 0.6 % of a
    2.5σ one-sided test), which costs a slightly larger variance and no measurable bias
    (sphere tests, mean z²).
    """
    if not sigma > 0 or model.half32 is None:
        return inl, b, ok
    inl, b = inl.copy(), b.copy()
    thr = np.float32(k_sigma * sigma)
    min_cos = np.float32(np.cos(np.radians(max_cone_deg)))
    # First round on every pixel without gathering columns: most have nothing to peel.
    j, r_j, cand = _mirror_suspect(model, model.s, inl, b, thr, min_cos)
    cand &= ok & (_count(inl) > 3)
    cols = np.flatnonzero(cand)
    j, r_j = j[cols], r_j[cols]
    for _ in range(rounds):
        if cols.size == 0:
            break
        sub_inl = inl[:, cols]
        lev = _leverage(sub_inl, model.ll6)
        h_j = lev[j, np.arange(cols.size)]
        z = r_j / np.sqrt(np.maximum(1.0 - h_j, np.float32(1e-3)))
        drop = z > thr
        cols, j, sub_inl = cols[drop], j[drop], sub_inl[:, drop]
        if cols.size == 0:
            break
        sub_inl[j, np.arange(cols.size)] = False
        b_new, ok_new = _fit(model.s[:, cols], sub_inl, model.lights32, model.ll6)
        # A drop that leaves lights not spanning 3-D is not made; that pixel stops.
        cols, sub_inl, b_new = cols[ok_new], sub_inl[:, ok_new], b_new[ok_new]
        inl[:, cols] = sub_inl
        b[cols] = b_new
        more = _count(sub_inl) > 3
        cols, sub_inl = cols[more], sub_inl[:, more]
        j, r_j, cand = _mirror_suspect(model, model.s[:, cols], sub_inl, b[cols], thr, min_cos)
        cols, j, r_j = cols[cand], j[cand], r_j[cand]
    return inl, b, ok


def _mirror_suspect(model, s, inl, b, thr, min_cos):
    """Per pixel: the inlier nearest the mirror direction of the fit b, its residual, and
    whether it lies within the cone and more than ``thr`` above the fit."""
    bc = b.astype(np.float32)
    rho = np.sqrt(np.einsum("ni,ni->n", bc, bc))
    cos_h = model.half32 @ (bc / np.maximum(rho, np.float32(1e-30))[:, None]).T
    np.copyto(cos_h, np.float32(-2.0), where=~inl)
    j = np.argmax(cos_h, axis=0)
    pick = np.arange(j.size)
    r_j = s[j, pick] - np.einsum("ni,ni->n", model.lights32[j], bc)
    return j, r_j, (cos_h[j, pick] >= min_cos) & (r_j > thr)


def cone_resolve(model, cand, inl, b, ok, sigma, *, cone_deg=20.0, k_sigma=1.5, free=4):
    """Solve again without the samples seen near the mirror direction of their light, and
    keep that solution where those samples prove to be highlights.

    A glossy surface (fired clay, consolidants) adds a highlight where the normal is near
    the half vector ĥ_k of light k and the camera direction.  Highlights a few per cent above
    the Lambertian shading pass the relative tolerance yet tilt the normal by a degree or
    more; the geometry tells where they can be.  The samples within ``cone_deg`` of the
    mirror direction of the fit are suspects when they are inliers more than σ above it;
    the pixel is then fitted again from the other lights (three suffice: select, refit,
    trim).  A highlight only adds light, so the new fit is kept only where the inliers left
    out sit above it: their mean excess over it exceeds ``k_sigma`` standard errors, the noise of
    the m samples and the new fit's own uncertainty at their mean direction ū (σ²·ūᵀM⁻¹ū,
    M = Σ l lᵀ over its inliers: extrapolating from a few grazing lights needs more proof).
    On a matte surface that happens by chance for ~7 % of the suspects (1.5σ), at the cost
    of a fit on fewer lights, still unbiased.  A cone taking ``free`` inliers or fewer needs
    no proof (little power, little loss).  With four inliers or fewer the fit bends to a
    highlight until its residual says little (leverage near 1; with three it is zero) and
    its normal may be off by degrees: there the cone is 10° wider and every sample in it is
    a suspect.  The 20° cone is where a Blinn–Phong lobe of exponent 40 still exceeds 8 % of
    its peak.  Broader lobes (Torrance–Sparrow, rough glaze) reach further, but a wider
    cone also takes more of the bright lights away, and an additive term common to all
    lights (stray light, interreflections) then flattens the normal: on the simulated hard
    scan (16 lights, stray light 1 %) a second pass at 30° flattened wedge walls by 0.9° on
    average (fused wedge depth error 3.4 → 5.8 µm), so there is none.
    """
    if not sigma > 0 or model.half32 is None:
        return inl, b
    bc = b.astype(np.float32)
    rho = np.sqrt(np.einsum("ni,ni->n", bc, bc))
    cos_h = model.half32 @ (bc / np.maximum(rho, np.float32(1e-30))[:, None]).T
    few = _count(inl) <= 4
    cone_cos = np.where(few, np.cos(np.radians(cone_deg + 10.0)), np.cos(np.radians(cone_deg)))
    near = (cos_h > cone_cos.astype(np.float32)) & model.valid
    # Only inliers are suspects: a highlight the fit already rejects needs no re-solve.
    above = np.subtract(model.s, model.lights32 @ bc.T)
    suspect = np.greater(above, np.float32(sigma), out=np.empty(above.shape, bool))
    suspect |= few[None]
    suspect &= near
    suspect &= inl
    outside = ~near
    outside &= model.valid
    redo = ok & np.any(suspect, axis=0) & (_count(outside) >= 3)
    cols = np.flatnonzero(redo)
    if cols.size == 0:
        return inl, b
    sub = model.sub(cols)
    near = _cols(near, cols)
    sub_inl = _cols(inl, cols)
    dropped = near & sub_inl
    # The cone's samples are no longer valid: no selection may re-admit them.
    sub.valid = sub.valid & ~near
    sub_cand = _cols(cand, cols) & ~near
    b0, ok0 = _fit(sub.s, sub_inl & ~near, sub.lights32, sub.ll6)
    inl2, b2, ok2 = _settle(sub, sub_cand, b0, ok0)
    # The evidence: the inliers the cone takes away must sit above the new fit.
    m = _count(dropped)
    excess = _select(dropped, sub.s - sub.lights32 @ b2.astype(np.float32).T).sum(axis=0)
    u = (dropped.T.astype(np.float32) @ sub.lights32) / m[:, None]
    x, ok_m = _solve_sym3(sub.ll6.T @ inl2.astype(np.float32), u.T, 1e-3)
    spread = np.einsum("ni,ni->n", u, x)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = excess / m / (sigma * np.sqrt(1.0 / m + spread))
    # Up to ``free`` inliers go without proof: a few samples give the test little power
    # (and with a sparse light set the re-solve's own uncertainty dominates it), while their
    # loss costs little.  Judging them too (16 lights, simulated hard scan) left weak lobes
    # in: fused wedge depth error 3.6 µm (free = 4), 4.3 µm (free = 0).
    take = ok2 & ok_m & ((z > k_sigma) | (m <= free))
    take = np.flatnonzero(take)
    inl, b = inl.copy(), b.copy()
    _set_cols(inl, cols[take], _cols(inl2, take))
    b[cols[take]] = _rows(b2, take)
    return inl, b


def consistent_least_squares(model, cand, inl, b, ok, sigma=0.0, *, cone_deg=20.0, k_sigma=2.5):
    """Least squares over each pixel's lit candidates where it explains all of them: no
    candidate beyond the inlier tolerance of that fit (|r| ≤ tolerance·max(l·b, 0) +
    abs_tol), and no lobe: the mean residual of the candidates within ``cone_deg`` of the
    fit's mirror direction (half vector near the normal, as in :func:`cone_resolve`) does
    not exceed that of the others by more than ``k_sigma`` standard errors
    (σ·√(1/m + 1/m_far); the others, not zero: a lobe lifts the least-squares fit, so that
    the samples away from it sit below it). Returns (inliers, b, ok).

    Under noise alone, least squares over every lit sample is the efficient estimate
    (Gauss–Markov), and every step that drops samples on a test (trim, mirror peeling, the
    highlight cone, the asymmetric reweighting) drops some good ones by chance: on a matte
    ball rendered by Mitsuba under 96 lights the robust fit's mean error was 7 % above
    least squares'. Where least squares leaves a sample outside the tolerance (a highlight,
    a cast shadow, an interreflection) the robust fit stands. A weak lobe that stays within
    the tolerance and too weak for the lobe test is left in. Rendered objects (Mitsuba, 96
    lights; mean error robust → this): matte ball 0.180° → 0.168° (least squares 0.168°),
    cat 3.44° → 3.42°, harvest 4.18° → 4.17°, dark glossy ball 4.48° → 4.47°; synthetic
    shading (bench/photometric_synthetic.py): Lambertian 96 lights 0.19° → 0.16°, broad lobes
    a little worse (16 lights 0.25·(n·h)²⁰: 1.40° → 1.45°; Torrance–Sparrow m = 0.4: 1.03° →
    1.07°): hence only where nothing corrects the normals later (photometric-only bundles).
    """
    b_ls, ok_ls = _fit(model.s, cand, model.lights32, model.ll6)
    r, tol, _ = model.residual(b_ls)
    # Beyond the tolerance either way: a sample the fit puts behind its terminator (l·b ≤ 0,
    # tolerance abs_tol) that reads lit is beyond it too.
    bad = cand & (np.abs(r) > tol)
    take = ok_ls & ~np.any(bad, axis=0)
    if model.half32 is not None and sigma > 0:
        # A lobe inside the tolerance: the candidates within `cone_deg` of the fit's mirror
        # direction sit above the others, significantly (one-sided).
        bc = b_ls.astype(np.float32)
        rho = np.sqrt(np.einsum("ni,ni->n", bc, bc))
        cos_h = model.half32 @ (bc / np.maximum(rho, np.float32(1e-30))[:, None]).T
        near = cand & (cos_h > np.float32(np.cos(np.radians(cone_deg))))
        far = cand & ~near
        m, m_far = _count(near), _count(far)
        excess = _select(near, r).sum(axis=0) / np.maximum(m, 1)
        excess -= _select(far, r).sum(axis=0) / np.maximum(m_far, 1)
        se = np.float32(sigma) * np.sqrt(1.0 / np.maximum(m, 1) + 1.0 / np.maximum(m_far, 1))
        lobe = (m > 0) & (m_far > 0) & (excess > k_sigma * se)
        take &= ~lobe
    b = np.where(take[:, None], b_ls, b)
    ok = np.where(take, ok_ls, ok)
    inl = _select(take[None, :], cand, inl)
    return inl, b, ok


def consensus_light_sets(inl_img: np.ndarray, ok_img: np.ndarray, window_px: int) -> np.ndarray:
    """Per pixel, the lights that the majority of the solved pixels of its ``window_px`` ×
    ``window_px`` neighbourhood keep as inliers: (K, H, W) bool from the per-pixel inlier
    sets ``inl_img`` (K, H, W) and the solved pixels ``ok_img`` (H, W).

    A majority (box) filter of the inlier mask, light by light: the neighbourhood's one
    light set, so that neighbouring normals are fitted from the same lights.
    """
    ok32 = ok_img.astype(np.float32)
    half = 0.5 * ndimage.uniform_filter(ok32, window_px, mode="constant")
    out = np.empty(inl_img.shape, dtype=bool)
    for k in range(inl_img.shape[0]):
        votes = ndimage.uniform_filter(inl_img[k] * ok32, window_px, mode="constant")
        np.greater(votes, half, out=out[k])
    return out


def coherent_normals(
    b_img: np.ndarray, ok_img: np.ndarray, window_px: int, max_turn_deg: float
) -> np.ndarray:
    """Pixels whose ``window_px`` × ``window_px`` neighbourhood of fitted normals is coherent:
    (H, W) bool from the scaled normals ``b_img`` (H, W, 3) and the solved pixels ``ok_img``.

    Coherent means the mean resultant length R̄ = |mean of the unit normals| of the window's
    solved pixels is at least cos ``max_turn_deg`` (Mardia & Jupp, *Directional Statistics*,
    2000, §9.2: R̄ = cos θ for directions spread at ±θ about their mean). One light set
    serves a neighbourhood only where its normals see the lights alike; where the surface
    turns within the window (a wedge's wall meeting its floor, a tight curve) a light's lobe
    tail or interreflection differs between its pixels, and a set that the majority keeps
    carries biases the minority's own fit had rejected.
    """
    norm = np.linalg.norm(b_img, axis=-1)
    ok = ok_img & (norm > 0)
    unit = np.where(ok[..., None], b_img / np.where(ok, norm, 1.0)[..., None], 0.0)
    ok32 = ok.astype(np.float32)
    count = ndimage.uniform_filter(ok32, window_px, mode="constant")
    mean = np.stack(
        [
            ndimage.uniform_filter(unit[..., c].astype(np.float32), window_px, mode="constant")
            for c in range(3)
        ],
        axis=-1,
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        r_bar = np.linalg.norm(mean, axis=-1) / count
    return ok & (r_bar >= np.cos(np.radians(max_turn_deg)))


def consensus_refit(model, inl, b, ok, consensus):
    """Fit each pixel again from its neighbourhood's light set ``consensus`` (K, n) bool
    (:func:`consensus_light_sets`) where that set explains its samples. Returns (inl, b, ok,
    taken), ``taken`` (n,) bool the pixels fitted from the neighbourhood's set.

    The robust fit chooses each pixel's inliers on its own; neighbouring pixels then use
    different light subsets, and the Lambertian departures within the tolerance (a lobe's
    tail, interreflection, subsurface light) bias each subset's normal differently: a
    patchwork of biases whose low frequencies integrate into height error (docs/
    benchmarks.md, issue 15, session 7: on native-random-0 the pixels whose count of lights
    differs from a neighbour's carry the default's height loss). One set over a
    neighbourhood makes the bias smooth (the fusion's normal-bias correction removes smooth
    biases). The pixel stands down, keeping its own set, where the neighbourhood's set
    leaves one of its samples beyond the inlier tolerance or behind the terminator (a cast
    shadow's edge, a highlight of its own), or spans fewer than three lights.
    """
    use = consensus & model.valid
    # Only the pixels whose neighbourhood set differs from their own are fitted again: a
    # second fit of every pixel cost up to 0.7 CPU s on the paper scan.
    cols = np.flatnonzero(ok & np.any(use != inl, axis=0))
    take = np.zeros(ok.shape, dtype=bool)
    if cols.size == 0:
        return inl, b, ok, take
    sub, use_c = model.sub(cols), _cols(use, cols)
    b_c, ok_c = _fit(sub.s, use_c, model.lights32, model.ll6)
    r, tol, front = sub.residual(b_c)
    explains = ok_c & ~np.any(use_c & ((np.abs(r) > tol) | ~front), axis=0)
    take[cols[explains]] = True
    b = b.copy()
    b[cols[explains]] = b_c[explains]
    inl = _select(take[None, :], use, inl)
    return inl, b, ok, take
