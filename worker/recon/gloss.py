"""Gloss from the photometric stack: a per-pixel Blinn–Phong specular strength and one
sharpness per scan, fitted from what the Lambertian model leaves unexplained.

The paper's future work asks for "determining the BRDF"; SCAN_BUNDLE.md's flat-fielded
shading of a frame is s_k = ρ·max(0, n·l_k) + gloss, relative to a white diffuser. With the
normals n known (the model's, which rest on the fringe heights as well as on the shading),
the model

    s_k = ρ·max(0, n·l_k) + k_s·max(0, n·ĥ_k)^α,      ĥ_k = (l_k + v)/|l_k + v|     (Blinn 1977)

is linear in (ρ, k_s) for a given α (v = (0, 0, −1), the telecentric camera). α is chosen
per scan by the least total squared residual over the pixels where (ρ, k_s) can be told
apart, then k_s per pixel.

Where it is not identifiable it says so instead of guessing: on a rig whose lights share
one polar angle, a pixel facing the camera sees the same n·l and the same n·ĥ under every
light, so a gloss there is indistinguishable from a brighter albedo (the columns of the
2 × 2 system are collinear). Those pixels take k_s from their identified neighbourhood
(normalised convolution, Knutsson & Westin 1993) and are flagged; where no neighbour is
identified, the scan's median. When the lobe does not explain the residual better than the
Lambertian model by more than the noise would (the data contradict it), the whole fit
stands down: k_s = 0 (matte), with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["EXPONENTS", "GlossResult", "fit_gloss"]

# Blinn–Phong sharpness candidates, log-spaced from a broad sheen to a near-mirror lobe.
EXPONENTS = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0)
VIEW = np.array([0.0, 0.0, -1.0])


@dataclass
class GlossResult:
    """strength: (H, W) float32 k_s relative to a white diffuser (0 off the mask);
    identified: (H, W) bool, where k_s was fitted rather than filled; exponent: α of the
    scan (None when the fit stood down); report: what was decided and why."""

    strength: np.ndarray
    identified: np.ndarray
    exponent: float | None
    report: dict = field(default_factory=dict)


def _sums(shading, lights, normals, mask, exponent, min_shading):
    """Per-pixel normal-equation sums of the two-column model over its usable samples."""
    half = lights + VIEW
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    n = normals[mask].astype(np.float64)  # (P, 3)
    s = shading[:, mask].astype(np.float64)  # (K, P)
    a = np.maximum(n @ lights.T, 0.0).T  # (K, P) n·l
    b = np.maximum(n @ half.T, 0.0).T ** exponent  # (K, P) (n·ĥ)^α
    # A sample is used where lit (n·l clear of the terminator) and not in a cast shadow
    # (shading above a small floor); NaN samples (reference too dark) drop out.
    use = (a > 0.1) & np.isfinite(s) & (s > min_shading)
    a, b, s = np.where(use, a, 0.0), np.where(use, b, 0.0), np.where(use, s, 0.0)
    return {
        "aa": (a * a).sum(0),
        "ab": (a * b).sum(0),
        "bb": (b * b).sum(0),
        "as": (a * s).sum(0),
        "bs": (b * s).sum(0),
        "ss": (s * s).sum(0),
        "count": use.sum(0),
    }


def _solve(t, max_collinearity, noise_sigma, max_strength_se):
    """(ρ, k_s, sse, sse of ρ alone, identified) per pixel from the sums `t`: identified
    where the columns are not collinear and k_s's standard error, σ·√(Σa²/det), is small."""
    aa, ab, bb, as_, bs, ss = t["aa"], t["ab"], t["bb"], t["as"], t["bs"], t["ss"]
    with np.errstate(divide="ignore", invalid="ignore"):
        rho1 = np.where(aa > 0, as_ / aa, 0.0)
        sse1 = ss - rho1 * as_
        cos2 = np.where(aa * bb > 0, ab * ab / (aa * bb), 1.0)
        det = aa * bb - ab * ab
        se = noise_sigma * np.sqrt(np.where(det > 0, aa / det, np.inf))
        ident = (cos2 < max_collinearity**2) & (t["count"] >= 4) & (se <= max_strength_se)
        ks = np.where(ident, (aa * bs - ab * as_) / np.where(ident, det, 1.0), 0.0)
        rho = np.where(ident, (bb * as_ - ab * bs) / np.where(ident, det, 1.0), rho1)
    # k_s ≥ 0: a negative lobe is no gloss (ρ alone then).
    neg = ks < 0
    ks = np.where(neg, 0.0, ks)
    rho = np.where(neg, rho1, rho)
    sse = ss - 2 * rho * as_ - 2 * ks * bs + rho * rho * aa + 2 * rho * ks * ab + ks * ks * bb
    return rho, ks, np.maximum(sse, 0.0), np.maximum(sse1, 0.0), ident, se


def _fill(strength, identified, mask, radius_px):
    """Normalised convolution of the identified strengths over the unidentified pixels."""
    sigma = max(radius_px / 2.0, 1.0)
    w = identified.astype(np.float32)
    num = cv2.GaussianBlur(strength * w, (0, 0), sigma)
    den = cv2.GaussianBlur(w, (0, 0), sigma)
    fallback = float(np.median(strength[identified])) if identified.any() else 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        filled = np.where(den > 1e-3, num / den, fallback)
    out = np.where(identified, strength, filled).astype(np.float32)
    return np.where(mask, out, 0.0).astype(np.float32)


def fit_gloss(
    shading: np.ndarray,
    light_dirs: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    noise_sigma: float,
    exponents: tuple[float, ...] = EXPONENTS,
    max_collinearity: float = 0.98,
    max_strength_se: float = 0.02,
    min_shading: float = 0.01,
    fill_radius_px: float = 16.0,
    min_identified: int = 200,
) -> GlossResult:
    """Fit the Blinn–Phong lobe (module docstring) to a flat-fielded photometric stack.

    Parameters
    ----------
    shading : (K, H, W) float
        Flat-fielded shading of the photometric frames (``radiometry.flat_field``), NaN
        where unusable.
    light_dirs : (K, 3) float
        Unit directions toward the sources (``photometric.light_directions``).
    normals : (H, W, 3) float
        Unit normals facing the camera (n_z < 0), NaN where none.
    mask : (H, W) bool
        The object's pixels.
    noise_sigma : float
        Standard deviation of one shading sample's noise (same units as ``shading``): the
        lobe must lower the residual by more than this noise explains, or the fit stands
        down.
    exponents : candidate α; max_collinearity : |cos| between the two columns above which
        a pixel's ρ and k_s cannot be told apart; max_strength_se : largest standard error
        of a fitted k_s (relative to white); min_shading : samples below are taken as
        cast shadow; fill_radius_px : neighbourhood of the fill; min_identified : fewest
        identified pixels for a scan-level α.
    """
    lights = np.asarray(light_dirs, np.float64)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    ok = mask & np.all(np.isfinite(normals), axis=-1)
    shape = mask.shape
    zero = np.zeros(shape, np.float32)
    none = np.zeros(shape, bool)
    if ok.sum() < min_identified or lights.shape[0] < 3:
        return GlossResult(zero, none, None, {"stood_down": "too few pixels or lights"})

    fits = {}
    for alpha in exponents:
        t = _sums(shading, lights, normals, ok, alpha, min_shading)
        fits[alpha] = _solve(t, max_collinearity, noise_sigma, max_strength_se)

    # α by Mallows' C_p over every pixel (Mallows 1973): a pixel's fit has a lobe where
    # the lobe is identifiable and ρ alone elsewhere, and each lobe costs 2σ², so a
    # candidate does not win by separating more pixels, only by explaining more.
    def cp(a):
        _, _, sse, sse1, ident, _ = fits[a]
        return float(np.where(ident, sse, sse1).sum()) + 2 * noise_sigma**2 * int(ident.sum())

    if not any(f[4].sum() >= min_identified for f in fits.values()):
        return GlossResult(
            zero,
            none,
            None,
            {
                "stood_down": "gloss not identifiable: the lights do not separate a lobe "
                "from the albedo anywhere (e.g. one polar angle and a flat object)"
            },
        )
    alpha = min((a for a in exponents if fits[a][4].sum() >= min_identified), key=cp)
    _, ks, sse, sse1, ident, se = fits[alpha]
    total, sse1_total = float(sse[ident].sum()), float(sse1[ident].sum())
    # The lobe adds one parameter per identified pixel: it must remove more squared
    # residual than noise alone would (σ² per pixel, the expected drop of a useless
    # regressor), by a clear margin, or the data say the surface is matte.
    n_pix = int(ident.sum())
    drop = sse1_total - total
    needed = 4.0 * noise_sigma**2 * n_pix
    report = {
        "candidate_exponent": alpha,
        "identified_fraction": round(int(ident.sum()) / int(ok.sum()), 4),
        "residual_drop": drop,
        "noise_drop": needed,
    }
    if drop <= needed:
        report["stood_down"] = "the lobe explains no more of the residual than the noise does"
        return GlossResult(zero, none, None, report)
    # A lobe within its own uncertainty is no evidence of gloss (small normal errors leave
    # residuals a weak lobe can fit).
    median_ks, median_se = float(np.median(ks[ident])), float(np.median(se[ident]))
    report["median_strength_se"] = median_se
    if median_ks <= 2 * median_se:
        report["stood_down"] = (
            f"no significant gloss: median strength {median_ks:.4f} within twice its "
            f"standard error {median_se:.4f}"
        )
        return GlossResult(zero, none, None, report)
    strength = np.zeros(shape, np.float32)
    identified = np.zeros(shape, bool)
    strength[ok] = ks.astype(np.float32)
    identified[ok] = ident
    strength = _fill(strength, identified, ok, fill_radius_px)
    report["median_strength"] = float(np.median(strength[identified]))
    return GlossResult(strength, identified, float(alpha), report)
