"""Photometric stereo: per-pixel normals and albedo from K ≥ 3 flat-fielded shading images.

Lambertian model (Digital Hammurabi, Kumar et al. 2003, Eqs. 1–2; Woodham 1980):

    s_k = ρ · V_k · max(0, n·l_k),   l_k = (sin θ_k sin φ_k, sin θ_k cos φ_k, −cos θ_k)

For the lights that see the point and lie in front of it (V_k = 1, n·l_k > 0) this is linear in
b = ρ·n: s_k = l_k·b, solved by least squares over K ≥ 3 such lights, n = b/|b|, ρ = |b|.
Real data breaks the model in some samples of every pixel: cast shadows (s ≈ 0), attached
shadows near the terminator (the max(0, ·) kink), specular highlights and interreflections
(s well above the fit).  Those samples are left out per pixel by an initial rank-based trim
followed by iterative re-selection against the current fit; everything is vectorised over
pixels by solving the 3×3 normal equations in closed form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PhotometricResult", "light_directions", "photometric_stereo"]

# About 4 M samples per (K, n) working array (16 MB float32), whatever the number of lights.
_CHUNK_SAMPLES = 1 << 22
_SIGMA_SAMPLE_PIXELS = 1 << 14


@dataclass(frozen=True)
class PhotometricResult:
    """Output of :func:`photometric_stereo`.

    normals : (H, W, 3) float32, unit, n_z < 0 (spec frame); NaN where not solved.
    albedo : (H, W) float32, ρ relative to the reference scale of the shading; NaN where not solved.
    residual : (H, W) float32, RMS of the inlier residuals divided by the albedo, i.e. the RMS
        misfit in units of n·l (0 for an exact fit, always 0 with exactly 3 inliers); NaN where
        not solved.
    lights_used : (H, W) int16, number of inlier lights (0 where not solved).
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    lights_used: np.ndarray


def light_directions(azimuth_deg, polar_deg) -> np.ndarray:
    """Unit directions toward the sources, ``(K, 3) float64``.

    l = (sin θ sin φ, sin θ cos φ, −cos θ) (SCAN_BUNDLE.md, the paper's Eq. 2).  ``polar_deg`` is
    a scalar or one angle per azimuth, in (0, 90) degrees.
    """
    phi = np.atleast_1d(np.asarray(azimuth_deg, dtype=np.float64))
    if phi.ndim != 1 or phi.size == 0 or not np.all(np.isfinite(phi)):
        raise ValueError("azimuth_deg must be a non-empty 1-D sequence of finite numbers")
    theta = np.asarray(polar_deg, dtype=np.float64)
    theta = np.full(phi.shape, float(theta)) if theta.ndim == 0 else theta
    if theta.shape != phi.shape:
        raise ValueError(f"polar_deg must be a scalar or have shape {phi.shape}")
    if not np.all((theta > 0) & (theta < 90)):
        raise ValueError("polar_deg must lie in (0, 90) degrees")
    p, t = np.deg2rad(phi), np.deg2rad(theta)
    return np.stack([np.sin(t) * np.sin(p), np.sin(t) * np.cos(p), -np.cos(t)], axis=1)


def _solve_sym3(m6: np.ndarray, rhs: np.ndarray, min_condition: float):
    """Solve M x = rhs for batched symmetric 3×3 M given as (N, 6) = (a, b, c, d, e, f).

    M = [[a, b, c], [b, d, e], [c, e, f]], by cofactors (exact, vectorised, no (N, 3, 3)
    temporaries).  Returns x (N, 3) float64, a bool mask of the systems whose normalised
    determinant det/(trace/3)^3 exceeds ``min_condition``, and M⁻¹ as (N, 6) (0 where not ok).
    """
    a, b, c, d, e, f = (m6[:, i].astype(np.float64) for i in range(6))
    cof = np.stack(
        [d * f - e * e, c * e - b * f, b * e - c * d, a * f - c * c, b * c - a * e, a * d - b * b],
        axis=1,
    )
    det = a * cof[:, 0] + b * cof[:, 1] + c * cof[:, 2]
    tr = (a + d + f) / 3.0
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = det > min_condition * tr**3
        inv6 = cof * np.where(ok, 1.0 / det, 0.0)[:, None]
    i11, i12, i13, i22, i23, i33 = inv6.T
    r0, r1, r2 = (rhs[:, i].astype(np.float64) for i in range(3))
    x = np.stack(
        [
            i11 * r0 + i12 * r1 + i13 * r2,
            i12 * r0 + i22 * r1 + i23 * r2,
            i13 * r0 + i23 * r1 + i33 * r2,
        ],
        axis=1,
    )
    return x, ok, inv6


def _fit(s, weight, lights32, ll6, *, leverage=False):
    """Weighted least-squares b per pixel; s, weight (K, N), weight 0 leaves a sample out.

    With ``leverage`` also returns h (K, N) = l_kᵀ M⁻¹ l_k, the hat-matrix diagonal of each
    inlier (unit weights), for deleted residuals r/(1 − h).
    """
    w = weight.astype(np.float32, copy=False)
    m6 = w.T @ ll6
    rhs = (w * s).T @ lights32
    enough = (weight > 0).sum(axis=0) >= 3
    b, ok, inv6 = _solve_sym3(m6, rhs, 1e-3)
    ok &= enough
    if not leverage:
        return b, ok
    # Off-diagonal terms of lᵀ M⁻¹ l appear twice.
    ll6d = ll6 * np.array([1, 2, 2, 1, 2, 1], dtype=np.float32)
    return b, ok, (inv6.astype(np.float32) @ ll6d.T).T


def _initial_inliers(s: np.ndarray, valid: np.ndarray, shadow_fraction: float):
    """Rank-based candidates: drop shadows and gross highlights (relative to upper quartile)."""
    k = s.shape[0]
    ranked = np.sort(np.where(valid, s, -np.inf), axis=0)
    n_valid = valid.sum(axis=0)
    # The upper quartile of the valid samples ignores up to a quarter of specular spikes.
    idx = np.clip(k - 1 - n_valid // 4, 0, k - 1)
    level = np.take_along_axis(ranked, idx[None, :], axis=0)[0]
    level = np.where(np.isfinite(level), level, 0.0).astype(np.float32)
    # Only gross highlights are cut here: when many lights are shadowed the upper quartile
    # can be a grazing sample well below the lit ones.  The robust fit copes with the rest.
    return valid & (s > shadow_fraction * level) & (s < 4.0 * level), level


def _l1_start(s, cand, lights32, ll6, delta, iterations=6):
    """Least absolute deviations over the candidates by IRLS (weights 1/max(|r|, delta))."""
    b, ok = _fit(s, cand, lights32, ll6)
    for _ in range(iterations):
        r = np.abs(s - lights32 @ b.astype(np.float32).T)
        w = np.where(cand, 1.0 / np.maximum(r, delta), 0.0).astype(np.float32)
        w /= np.maximum(w.max(axis=0, keepdims=True), np.float32(1e-30))
        b_new, ok_new = _fit(s, w, lights32, ll6)
        b = np.where(ok_new[:, None], b_new, b)
        ok |= ok_new
    return b, ok


class _Model:
    """Per-chunk constants and the tolerance model shared by the robust-fit steps."""

    def __init__(self, s, valid, lights32, ll6, shadow_fraction, tolerance, abs_tol):
        self.s, self.valid, self.lights32, self.ll6 = s, valid, lights32, ll6
        self.shadow = np.float32(shadow_fraction)
        self.tolerance = np.float32(tolerance)
        self.abs_tol = np.float32(abs_tol)

    def sub(self, cols):
        """The same model restricted to the pixels ``cols``."""
        return _Model(
            self.s[:, cols],
            self.valid[:, cols],
            self.lights32,
            self.ll6,
            self.shadow,
            self.tolerance,
            self.abs_tol,
        )

    def residual(self, b, cols=slice(None)):
        """Signed residual s − l·b, the tolerance and the terminator test, each (K, n)."""
        b32 = b.astype(np.float32)
        pred = self.lights32 @ b32.T
        rho = np.sqrt(np.einsum("ni,ni->n", b32, b32))
        front = pred > self.shadow * rho
        # In place: these (K, n) passes dominate the cost of the whole fit.
        r = np.subtract(self.s[:, cols], pred)
        tol = np.maximum(pred, np.float32(0.0), out=pred)
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
        """Consensus count, minus candidates far below the fit, minus a tie-breaking misfit.

        Samples above the shadow threshold that sit far BELOW a fit are implausible (only a
        penumbra does that), whereas highlights and interreflections sit above it: a fit
        through highlights leaves good samples below it and is penalised.
        """
        r, tol, front = self.residual(b)
        inl = self.valid & front & (np.abs(r) <= tol)
        below = cand & (r < -tol)
        m = inl.sum(axis=0)
        misfit = np.where(inl, (r / tol) ** 2, 0.0).sum(axis=0) / np.maximum(m, 1)
        return np.where(ok, m - below.sum(axis=0) - 0.01 * misfit, -np.inf)

    def trim(self, inl, b, ok):
        """Backward elimination on studentised residuals r/sqrt(1 − h), one sample per round.

        Removing one sample at a time, judged by the residual it would have if left out of
        the fit, catches high-leverage highlights that hide from the raw residuals.
        """
        inl = inl.copy()
        b, ok = b.copy(), ok.copy()
        cols = np.flatnonzero(inl.sum(axis=0) > 3)
        # Few rounds: the batch removal below empties most pixels in one or two, and what a
        # round cap leaves is caught by the tolerance test of the next selection.
        for _ in range(min(self.s.shape[0] - 3, 6)):
            if cols.size == 0:
                break
            sub = inl[:, cols]
            r, tol, _ = self.residual(b[cols], cols)
            raw = np.where(sub, np.abs(r) / tol, 0.0)
            # Leverage rarely exceeds 0.9 with four or more lights, so a sample whose raw
            # ratio is below 0.3 cannot be the worst misfit: skip those pixels cheaply.
            near = raw.max(axis=0) > 0.3
            cols, sub, raw = cols[near], sub[:, near], raw[:, near]
            if cols.size == 0:
                break
            _, _, lev = _fit(self.s[:, cols], sub, self.lights32, self.ll6, leverage=True)
            # Externally studentised: the deleted residual r/(1 − h) has variance
            # σ²/(1 − h), so r/sqrt(1 − h) is compared with the tolerance.
            ratio = raw / np.sqrt(np.maximum(1.0 - lev, np.float32(1e-3)))
            n_in = sub.sum(axis=0)
            worst = ratio.max(axis=0)
            bad = (worst > 1.0) & (n_in > 3)
            cols, sub, ratio, n_in, worst = (
                cols[bad],
                sub[:, bad],
                ratio[:, bad],
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
            inl[:, cols] &= ~drop
            b_new, ok_new = _fit(self.s[:, cols], inl[:, cols], self.lights32, self.ll6)
            # A removal that leaves lights not spanning 3-D is undone and ends that pixel.
            undo = ~ok_new
            inl[:, cols[undo]] |= drop[:, undo]
            cols = cols[ok_new]
            b[cols], ok[cols] = b_new[ok_new], True
        return inl, b, ok


def _hypotheses(model, cand, delta):
    """Alternative starts: L1 over all candidates; LS without the brightest one or two
    (a specular lobe covers one or two neighbouring lights) or without the darkest."""
    s = model.s
    k, n = s.shape
    cols = np.arange(n)
    ranked = np.argsort(np.where(cand, s, -np.inf), axis=0)
    n_cand = cand.sum(axis=0)
    drops = (
        [ranked[k - 1]],
        [ranked[k - 1], ranked[k - 2]],
        [ranked[np.clip(k - n_cand, 0, k - 1), cols]],
    )
    yield _l1_start(s, cand, model.lights32, model.ll6, delta)
    for drop in drops:
        c = cand.copy()
        for d in drop:
            c[d, cols] = False
        yield _fit(s, c, model.lights32, model.ll6)


def _settle(model, cand, b0, ok0):
    """From a start b0: select the consistent samples, refit where they changed, trim."""
    inl = model.select(b0)
    inl = np.where((inl.sum(axis=0) >= 3)[None, :], inl, cand)
    b, ok = b0.copy(), ok0.copy()
    moved = np.flatnonzero(np.any(inl != cand, axis=0) | ~ok)
    if moved.size:
        b[moved], ok[moved] = _fit(model.s[:, moved], inl[:, moved], model.lights32, model.ll6)
    return model.trim(inl, b, ok)


def _robust_fit(model, cand, iterations):
    """LS start → select → trim; where that rejects anything, also try the alternative starts
    and keep the best by score; then re-admission rounds until the sets settle.

    Pixels whose candidates in front of the terminator all agree with their least-squares
    fit (most of a clean scan) leave after the first pass, so the costly alternatives run on
    the few that need them.
    """
    b0, ok0 = _fit(model.s, cand, model.lights32, model.ll6)
    inl, b, ok = _settle(model, cand, b0, ok0)
    # Candidates left out only for lying beyond the terminator are not outliers; a pixel
    # needs the alternatives when a sample in front of it misfits.
    _, _, front = model.residual(b)
    cols = np.flatnonzero(~ok | np.any(cand & ~inl & front, axis=0))
    if cols.size:
        sub = model.sub(cols)
        sub_cand = cand[:, cols]
        best_inl, best_b, best_ok = inl[:, cols], b[cols], ok[cols]
        best_sc = sub.score(best_b, best_ok, sub_cand)
        for h_b, h_ok in _hypotheses(sub, sub_cand, max(float(model.abs_tol), 1e-4)):
            h_inl, h_b, h_ok = _settle(sub, sub_cand, h_b, h_ok)
            sc = sub.score(h_b, h_ok, sub_cand)
            better = sc > best_sc
            best_b = np.where(better[:, None], h_b, best_b)
            best_ok = np.where(better, h_ok, best_ok)
            best_inl = np.where(better[None, :], h_inl, best_inl)
            best_sc = np.where(better, sc, best_sc)
        inl[:, cols], b[cols], ok[cols] = best_inl, best_b, best_ok

    # Only pixels whose fit changed after their last selection can re-admit samples.
    for _ in range(iterations):
        if cols.size == 0:
            break
        sub = model.sub(cols)
        new = sub.select(b[cols])
        # Re-admission never drops a pixel below three lights.
        new = np.where((new.sum(axis=0) >= 3)[None, :], new, inl[:, cols])
        moved = np.any(new != inl[:, cols], axis=0)
        cols, new = cols[moved], new[:, moved]
        if cols.size == 0:
            break
        sub = model.sub(cols)
        b_new, ok_new = _fit(sub.s, new, sub.lights32, sub.ll6)
        new, b_new, ok_new = sub.trim(new, b_new, ok_new)
        # Keep the previous solution where the new set does not span 3-D.
        take = ok_new | ~ok[cols]
        cols, new, b_new, ok_new = cols[take], new[:, take], b_new[take], ok_new[take]
        inl[:, cols], b[cols], ok[cols] = new, b_new, ok_new
    return b, ok, inl


def _validate(shading, light_dirs, mask):
    s = np.asarray(shading)
    if s.ndim != 3 or s.shape[0] < 3:
        raise ValueError(f"shading must have shape (K >= 3, H, W), got {s.shape}")
    if not np.issubdtype(s.dtype, np.number) or np.iscomplexobj(s):
        raise ValueError(f"shading must be real numeric, got dtype {s.dtype}")
    lights = np.asarray(light_dirs, dtype=np.float64)
    if lights.shape != (s.shape[0], 3) or not np.all(np.isfinite(lights)):
        raise ValueError(f"light_dirs must be finite with shape ({s.shape[0]}, 3)")
    norm = np.linalg.norm(lights, axis=1)
    if np.any(norm < 1e-9):
        raise ValueError("light_dirs contains a zero vector")
    lights = lights / norm[:, None]
    if np.linalg.matrix_rank(lights, tol=1e-6) < 3:
        raise ValueError("light_dirs must span 3-D (at least three non-coplanar directions)")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != s.shape[1:] or mask.dtype != bool:
            raise ValueError(f"mask must be a bool array of shape {s.shape[1:]}")
    return s, lights, mask


def _estimate_sigma(s, valid, lights32, ll6, shadow_fraction, tolerance):
    """Robust global σ of the Lambertian residual from an evenly strided pixel sample.

    The sample is fitted robustly with the relative tolerance alone; σ is the scaled MAD of
    the residuals of the samples it keeps.
    """
    cand, _ = _initial_inliers(s, valid, shadow_fraction)
    model = _Model(s, valid, lights32, ll6, shadow_fraction, tolerance, 0.0)
    b, ok, inl = _robust_fit(model, cand, 3)
    keep = inl & ok[None, :]
    if not keep.any():
        return 0.0
    resid = np.abs(s - lights32 @ b.astype(np.float32).T)[keep]
    dof = float(np.mean(keep.sum(axis=0)[ok]))
    # MAD of residuals of a 3-parameter fit from m samples under-reads σ by sqrt((m-3)/m).
    return float(1.4826 * np.median(resid) * np.sqrt(dof / max(dof - 3.0, 1.0)))


def photometric_stereo(
    shading: np.ndarray,
    light_dirs: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    shadow_fraction: float = 0.1,
    outlier_tolerance: float = 0.08,
    noise_sigma: float | None = None,
    noise_k: float = 3.0,
    max_iterations: int = 6,
) -> PhotometricResult:
    """Robust Lambertian photometric stereo, vectorised over pixels.

    Parameters
    ----------
    shading : (K, H, W) float
        Flat-fielded shading s_k = ρ·V·max(0, n·l_k) (see :func:`radiometry.flat_field`),
        NaN for unusable samples.  Any per-frame directions, K ≥ 3.
    light_dirs : (K, 3) float
        Source directions in the spec frame (:func:`light_directions`); normalised here.
    mask : (H, W) bool, optional
        Pixels to solve; others are NaN / 0.
    shadow_fraction : float
        A sample is a shadow candidate when its predicted n·l is below this value (attached
        shadow, too close to the terminator) or, in the first guess, when it is below this
        fraction of the pixel's upper-quartile sample.
    outlier_tolerance : float
        Relative misfit allowed beyond noise: a sample is an inlier when
        |s − l·b| ≤ outlier_tolerance·(l·b) + noise_k·noise_sigma.  Covers BRDF departures
        from Lambert and mild interreflection; highlights and cast shadows exceed it.
    noise_sigma : float, optional
        σ of the shading noise; estimated robustly from the data when None.
    max_iterations : int
        Re-selection rounds after the first fit (stops early when the inlier sets settle).

    Returns
    -------
    PhotometricResult
        Pixels with fewer than 3 usable lights, or whose usable lights do not span 3-D, are NaN.
        Normals are clamped to n_z ≤ −1e-3 (a surface the camera sees faces it).
    """
    s_all, lights, mask = _validate(shading, light_dirs, mask)
    if not (0.0 <= shadow_fraction < 1.0):
        raise ValueError(f"shadow_fraction must lie in [0, 1), got {shadow_fraction}")
    if outlier_tolerance <= 0:
        raise ValueError(f"outlier_tolerance must be > 0, got {outlier_tolerance}")
    if noise_sigma is not None and not (noise_sigma >= 0):
        raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma}")
    k, h, w = s_all.shape
    lights32 = lights.astype(np.float32)
    iu = np.triu_indices(3)
    ll6 = (lights[:, :, None] * lights[:, None, :])[:, iu[0], iu[1]].astype(np.float32)

    flat = s_all.reshape(k, h * w)
    pix = np.flatnonzero(mask.ravel()) if mask is not None else np.arange(h * w)
    normals = np.full((h * w, 3), np.nan, dtype=np.float32)
    albedo = np.full(h * w, np.nan, dtype=np.float32)
    residual = np.full(h * w, np.nan, dtype=np.float32)
    used = np.zeros(h * w, dtype=np.int16)

    if noise_sigma is None and pix.size:
        s_sub = flat[:, pix[:: max(1, pix.size // _SIGMA_SAMPLE_PIXELS)]].astype(np.float32)
        valid_sub = np.isfinite(s_sub)
        noise_sigma = _estimate_sigma(
            np.where(valid_sub, s_sub, np.float32(0.0)),
            valid_sub,
            lights32,
            ll6,
            shadow_fraction,
            outlier_tolerance,
        )
    abs_tol = np.float32(noise_k * (noise_sigma or 0.0))

    chunk = max(4096, _CHUNK_SAMPLES // k)
    for start in range(0, pix.size, chunk):
        # Without a mask the chunks are contiguous slices: no gather copy of the stack.
        idx = (
            pix[start : start + chunk]
            if mask is not None
            else slice(start, min(start + chunk, pix.size))
        )
        s = flat[:, idx].astype(np.float32)
        valid = np.isfinite(s)
        s = np.where(valid, s, np.float32(0.0))
        cand, _ = _initial_inliers(s, valid, shadow_fraction)
        model = _Model(s, valid, lights32, ll6, shadow_fraction, outlier_tolerance, abs_tol)
        b, ok, inl = _robust_fit(model, cand, max_iterations)
        rho = np.linalg.norm(b, axis=1)
        ok &= rho > 0
        n = b / np.where(ok, rho, 1.0)[:, None]
        n[:, 2] = np.minimum(n[:, 2], -1e-3)
        n /= np.linalg.norm(n, axis=1)[:, None]
        pred = lights32 @ b.astype(np.float32).T
        m = inl.sum(axis=0)
        sq = np.where(inl, (s - pred) ** 2, 0.0).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            res = np.sqrt(sq / np.maximum(m, 1)) / rho
        normals[idx] = np.where(ok[:, None], n, np.nan)
        albedo[idx] = np.where(ok, rho, np.nan)
        residual[idx] = np.where(ok, res, np.nan)
        used[idx] = np.where(ok, m, 0)

    return PhotometricResult(
        normals=normals.reshape(h, w, 3),
        albedo=albedo.reshape(h, w),
        residual=residual.reshape(h, w),
        lights_used=used.reshape(h, w),
    )
