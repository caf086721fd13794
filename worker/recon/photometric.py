"""Photometric stereo: per-pixel normals and albedo from K ≥ 3 flat-fielded shading images.

Lambertian model (Digital Hammurabi, Kumar et al. 2003, Eqs. 1–2; Woodham 1980):

    s_k = ρ · V_k · max(0, n·l_k),   l_k = (sin θ_k sin φ_k, sin θ_k cos φ_k, −cos θ_k)

For the lights that see the point and lie in front of it (V_k = 1, n·l_k > 0) this is linear in
b = ρ·n: s_k = l_k·b, solved by least squares over K ≥ 3 such lights, n = b/|b|, ρ = |b|.
Real data breaks the model in some samples of every pixel: cast shadows (s ≈ 0), attached
shadows near the terminator (the max(0, ·) kink), specular highlights and interreflections
(s well above the fit).  Those samples are left out per pixel by an initial rank-based trim
followed by consensus, trimming and re-selection against the current fit
(:mod:`worker.recon.photometric_fit`); everything is vectorised over pixels by solving the 3×3
normal equations in closed form.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worker.recon.parallel import run_blocks
from worker.recon.photometric_fit import (
    _DENSE_LIGHTS,
    Model,
    _count,
    _select,
    asymmetric_refine,
    coherent_normals,
    cone_resolve,
    consensus_light_sets,
    consensus_refit,
    consistent_least_squares,
    estimate_sigma,
    initial_inliers,
    mirror_trim,
    robust_fit,
)

__all__ = ["PhotometricResult", "light_directions", "photometric_stereo"]

# About 1 M samples per (K, n) working array (4 MB float32), whatever the number of lights:
# small enough to stay in cache and to share out between threads.
_CHUNK_SAMPLES = 1 << 20
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
    outliers : (H, W) int16, number of samples the fit left out although they read above the
        noise floor (3σ of the shading noise) in front of its terminator (n·l above
        ``shadow_fraction``): highlights, interreflections, cast shadows' penumbrae.
    noise_sigma : float, σ of the shading noise used for the tolerances (given or estimated).
    consensus : (H, W) bool, pixels fitted from their neighbourhood's light set
        (``consensus_window_px``); None when that step is off.
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    lights_used: np.ndarray
    noise_sigma: float = 0.0
    outliers: np.ndarray | None = None
    consensus: np.ndarray | None = None


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


def _row_norms(v: np.ndarray) -> np.ndarray:
    """|v| of each row of an (N, 3) float64 array, bit for bit ``np.linalg.norm(v, axis=1)``
    (whose sum of squares runs x² + y², then + z²), in column passes: the 3-element
    reduction per row costs several times more."""
    sq = v * v
    out = np.add(sq[:, 0], sq[:, 1])
    out += sq[:, 2]
    return np.sqrt(out, out=out)


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
    highlight_rounds: int | None = None,
    highlight_cone_deg: float | None = 20.0,
    least_squares_when_consistent: bool = False,
    consensus_window_px: int = 0,
    consensus_max_turn_deg: float = 10.0,
    workers: int = 1,
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
    highlight_rounds : int, optional
        Rounds of :func:`photometric_fit.mirror_trim` (0: off), which peels specular samples
        nearest the mirror direction of the fit while they sit significantly above it.
        None: 12 with 32 lights or more, else 0.
    highlight_cone_deg : float or None
        Half-angle between normal and half vector within which a light's sample may be a
        highlight: :func:`photometric_fit.cone_resolve` fits such pixels again without
        those samples and keeps the new fit where they sit significantly above it.  None:
        off.  Both highlight steps take the view direction (0, 0, −1) of the spec's
        orthographic camera.
    least_squares_when_consistent : bool
        Where least squares over the pixel's lit candidates leaves every one of them within
        the inlier tolerance and shows no lobe near its mirror direction, take it instead of
        the robust fit (:func:`photometric_fit.consistent_least_squares`): the robust steps
        then act only where the data show an outlier. Used for bundles without fringe
        heights (never worse than least squares on a matte object).
    consensus_window_px : int
        0: off. Otherwise, after every pixel's own fit, fit each pixel again from the light
        set that the majority of its ``consensus_window_px``-wide neighbourhood keeps
        (:func:`photometric_fit.consensus_refit`), where that set explains its samples.
    consensus_max_turn_deg : float
        The neighbourhood's set stands down (each pixel keeps its own) where the window's
        fitted normals spread by more than ± this angle about their mean
        (:func:`photometric_fit.coherent_normals`).
    workers : int
        Threads sharing the chunks of pixels (the result does not depend on it).

    Returns
    -------
    PhotometricResult
        Pixels with fewer than 3 usable lights, or whose usable lights do not span 3-D, are NaN.
        Normals are clamped to n_z ≤ −1e-3 (a surface the camera sees faces it).
    """
    s_all, lights, mask = _validate(shading, light_dirs, mask)
    if not (0.0 <= shadow_fraction < 1.0):
        raise ValueError(f"shadow_fraction must lie in [0, 1), got {shadow_fraction}")
    if consensus_window_px < 0 or (consensus_window_px and not 0 < consensus_max_turn_deg <= 180):
        raise ValueError(
            "consensus_window_px must be >= 0 and consensus_max_turn_deg in (0, 180], got "
            f"{consensus_window_px} and {consensus_max_turn_deg}"
        )
    if outlier_tolerance <= 0:
        raise ValueError(f"outlier_tolerance must be > 0, got {outlier_tolerance}")
    if noise_sigma is not None and not (noise_sigma >= 0):
        raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma}")
    k, h, w = s_all.shape
    lights32 = lights.astype(np.float32)
    # Half vectors between each light and the view direction (0, 0, −1) of the spec's
    # orthographic camera: where specular highlights peak.
    half = lights + np.array([0.0, 0.0, -1.0])
    half32 = (half / np.linalg.norm(half, axis=1, keepdims=True)).astype(np.float32)
    iu = np.triu_indices(3)
    ll6 = (lights[:, :, None] * lights[:, None, :])[:, iu[0], iu[1]].astype(np.float32)

    flat = s_all.reshape(k, h * w)
    pix = np.flatnonzero(mask.ravel()) if mask is not None else np.arange(h * w)
    normals = np.full((h * w, 3), np.nan, dtype=np.float32)
    albedo = np.full(h * w, np.nan, dtype=np.float32)
    residual = np.full(h * w, np.nan, dtype=np.float32)
    used = np.zeros(h * w, dtype=np.int16)
    rejected = np.zeros(h * w, dtype=np.int16)

    if noise_sigma is None and pix.size:
        s_sub = flat[:, pix[:: max(1, pix.size // _SIGMA_SAMPLE_PIXELS)]].astype(np.float32)
        valid_sub = np.isfinite(s_sub)
        noise_sigma = estimate_sigma(
            np.where(valid_sub, s_sub, np.float32(0.0)),
            valid_sub,
            lights32,
            ll6,
            shadow_fraction,
            outlier_tolerance,
        )
    abs_tol = np.float32(noise_k * (noise_sigma or 0.0))

    # Peeling pays with dense light sets; with a few lights each peeled sample is a large
    # share of the constraints, and an additive term common to all lights (stray light,
    # interreflections) then flattens the normal: on the simulated hard scan (16 lights,
    # stray light 1 %) peeling flattened wedge walls by 0.4° on average.
    rounds = (12 if k >= _DENSE_LIGHTS else 0) if highlight_rounds is None else highlight_rounds
    chunk = max(4096, _CHUNK_SAMPLES // k)

    def chunk_of(start: int):
        # Without a mask the chunks are contiguous slices: no gather copy of the stack.
        idx = (
            pix[start : start + chunk]
            if mask is not None
            else slice(start, min(start + chunk, pix.size))
        )
        s = flat[:, idx].astype(np.float32)  # a copy: zeroed in place below
        valid = np.isfinite(s)
        # The unusable samples zeroed (what nan_to_num does, in a fraction of its passes).
        np.copyto(s, np.float32(0.0), where=~valid)
        cand, _ = initial_inliers(s, valid, shadow_fraction, abs_tol)
        model = Model(s, valid, lights32, ll6, shadow_fraction, outlier_tolerance, abs_tol, half32)
        return idx, s, valid, cand, model

    def fit(model, cand):
        b, ok, inl = robust_fit(model, cand, max_iterations)
        if rounds:
            inl, b, ok = mirror_trim(model, inl, b, ok, noise_sigma or 0.0, rounds=rounds)
        if highlight_cone_deg:
            inl, b = cone_resolve(
                model, cand, inl, b, ok, noise_sigma or 0.0, cone_deg=highlight_cone_deg
            )
        b = asymmetric_refine(model, inl, b, ok, noise_sigma or 0.0)
        if least_squares_when_consistent:
            inl, b, ok = consistent_least_squares(model, cand, inl, b, ok, noise_sigma or 0.0)
        return inl, b, ok

    def finish(idx, s, valid, inl, b, ok) -> None:
        rho = _row_norms(b)
        ok &= rho > 0
        n = b / np.where(ok, rho, 1.0)[:, None]
        n[:, 2] = np.minimum(n[:, 2], -1e-3)
        n /= _row_norms(n)[:, None]
        pred = lights32 @ b.astype(np.float32).T
        m = _count(inl)
        sq = _select(inl, (s - pred) ** 2).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            res = np.sqrt(sq / np.maximum(m, 1)) / rho
        normals[idx] = np.where(ok[:, None], n, np.nan)
        albedo[idx] = np.where(ok, rho, np.nan)
        residual[idx] = np.where(ok, res, np.nan)
        used[idx] = np.where(ok, m, 0)
        lit = valid & (s > abs_tol) & (pred > np.float32(shadow_fraction) * rho[None, :])
        rejected[idx] = np.where(ok, _count(lit & ~inl), 0)

    def solve(start: int) -> None:
        idx, s, valid, cand, model = chunk_of(start)
        inl, b, ok = fit(model, cand)
        if consensus_window_px:
            # Kept for the second pass, which needs every pixel's neighbours fitted.
            inl_all[:, idx], b_all[idx], ok_all[idx] = inl, b, ok
        else:
            finish(idx, s, valid, inl, b, ok)

    def resolve(start: int) -> None:
        idx, s, valid, _, model = chunk_of(start)
        inl, b, ok, consensus_taken[idx] = consensus_refit(
            model, inl_all[:, idx], b_all[idx], ok_all[idx], consensus[:, idx]
        )
        finish(idx, s, valid, inl, b, ok)

    if consensus_window_px:
        inl_all = np.zeros((k, h * w), dtype=bool)
        b_all = np.zeros((h * w, 3))
        ok_all = np.zeros(h * w, dtype=bool)
        consensus_taken = np.zeros(h * w, dtype=bool)

    # Pixels are independent: chunks run in threads (numpy releases the GIL on the arrays).
    run_blocks(solve, range(0, pix.size, chunk), workers=workers)
    if consensus_window_px:
        consensus = consensus_light_sets(
            inl_all.reshape(k, h, w), ok_all.reshape(h, w), consensus_window_px
        ).reshape(k, h * w)
        coherent = coherent_normals(
            b_all.reshape(h, w, 3),
            ok_all.reshape(h, w),
            consensus_window_px,
            consensus_max_turn_deg,
        ).reshape(h * w)
        np.copyto(consensus, inl_all, where=~coherent[None, :])
        run_blocks(resolve, range(0, pix.size, chunk), workers=workers)

    return PhotometricResult(
        normals=normals.reshape(h, w, 3),
        albedo=albedo.reshape(h, w),
        residual=residual.reshape(h, w),
        lights_used=used.reshape(h, w),
        noise_sigma=float(noise_sigma or 0.0),
        outliers=rejected.reshape(h, w),
        consensus=consensus_taken.reshape(h, w) if consensus_window_px else None,
    )
