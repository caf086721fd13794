"""Scale by scale, how far the fused heights should follow the fringe heights (issue 15, item 4).

The default fusion (`fusion.fuse_default`) weighs every slope against every fringe height by
white-noise variances, which sets one crossover scale per pixel: below it the normals
decide, above it the fringes. Neither noise is white. Photometric normals carry a bias
correlated over tens of pixels (interreflection, light inside the clay, gloss) that their
residuals do not show, and the fringe heights' noise is red too (projector pixels, speckle
of the phase, per-azimuth shadows). Where the normals' bias at some scale exceeds the
fringes' noise at that scale the fused surface is wrong there, and the fringe heights show
it: this module measures both error spectra on the scan and moves the fused heights toward
the fringes band by band, by the Wiener gain of each band, region by region.

Model, for each band b of a Gaussian scale space (difference of normalised Gaussians of
σ_b and σ_{b+1} px, Burt & Adelson's Laplacian pyramid without decimation):

    D = f − G_β * h = e_f − G_β * e_h

h the fused heights (error e_h, mostly the normals' in the bands where the fusion follows
them), f the fringe heights (error e_f), G_β the blur by which the fringes are smoother than
the normals (`quality.fringe_blur_px`: light inside the clay, a defocused projector), so that
a wedge the fringes round does not read as the normals' error. With e_f and e_h independent,
E[D_b²] = v_f,b + v_h,b, and the least-squares estimate of the band's error of h is
α·D_b with the Wiener gain α = max(0, 1 − v_f,b/E[D_b²]) (Wiener 1949; the local, adaptive
form of Lee 1980): 0 where the disagreement is within the fringes' noise (the step stands
down), → 1 where it is far above.

- v_f,b, the fringes' noise in band b, is measured on the scan: the differences of the
  azimuths' own heights (`Measurements.fringe_azimuth_heights_um`) cancel the surface and
  every error the azimuths share, so their band variance over the predicted white variance
  σ_a² + σ_b² of the phase noise gives the noise's colour κ_b per band
  (`fringe_noise_colour`). Per pixel v_f,b = κ_b·c_b·⟨σ_ph²⟩ (c_b the band filter's white-
  noise gain, ⟨⟩ the band's local mean), plus the crease model error where the fringes
  cannot follow a bend within a pixel (`quality.crease_sigma_um`), which enters as a weight:
  each fringe height counts σ_ph²/(σ_ph² + crease²), so wedge rims and bottoms take their
  band from their neighbours.
- E[D_b²] is the local mean of D_b² over a window of 2·σ_{b+1} (the band's neighbourhood).
- Large local disagreements — a cliff the fringes mix, a wedge the blur model misses, an
  unwrapping error — are not a smooth bias of the normals: each band's correction is also
  multiplied by the Cauchy weight 1/(1 + D_b²/(k²·E)), k = `outlier_sigmas`, and fringe
  heights off the fused surface by more than k_out·σ are left out altogether.

The errors the azimuths share (a common phase bias, pixel mixing at creases) are not in κ:
where they dominate, the gain overestimates the fringes. They dominate in the bands finer
than the fringe heights resolve: a band whose finest scale is below the fringes' whole blur
σ_r (their blur relative to the normals, the camera's PSF and the pixel's area, in
quadrature) stands down — the fringes keep less than half of a detail of scale below σ_r,
transfer s²/(s² + σ_r²) — and is left to the fusion (`resolution_px`). The bench shows
whether the step earns its place (docs/reconstruction.md). All functions are pure (arrays in, arrays out).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from worker.recon.arrays import fast_median

__all__ = [
    "BAND_SCALES_PX",
    "BandCorrection",
    "band_noise_gain",
    "band_wiener_correct",
    "fringe_noise_colour",
]

# Gaussian scales (px) whose differences are the bands: 0 is the pixel itself; the last
# band is everything coarser than 32 px.
BAND_SCALES_PX: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
# χ²₁'s median: a median of squared Gaussian values over it estimates their variance.
_CHI2_1_MEDIAN = 0.4549
# Pixels (at most) over which the noise colour is estimated: a central crop, enough for a
# scan-wide statistic, cheap at 1.3 Mpx.
_COLOUR_CROP_PX = 512


@dataclass(frozen=True)
class BandCorrection:
    """`band_wiener_correct`'s result: heights, and per band (finest first) the mean Wiener
    gain over the mask and the share of mask pixels where it is above 0 (where the step
    acted; elsewhere it stood down)."""

    height_um: np.ndarray
    mean_gain: tuple[float, ...]
    acting_share: tuple[float, ...]


def _smooth(x: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of σ px (zero outside the frame); σ ≥ 4 on a grid decimated by σ/4 (area
    mean), then bilinear back: the extra box blur, variance (σ/4)²/12, is under 1 % of σ²."""
    if sigma_px <= 0:
        return x
    step = int(sigma_px // 4) if sigma_px >= 8 else 1
    if step > 1:
        # Padded with zeros (the constant border) to whole steps, so that the coarse grid's
        # cells are exactly step × step pixels and the way back lands on the same pixels.
        rows, cols = x.shape
        pr, pc = -rows % step, -cols % step
        padded = np.pad(x, ((0, pr), (0, pc))) if pr or pc else x
        small = cv2.resize(
            padded,
            ((cols + pc) // step, (rows + pr) // step),
            interpolation=cv2.INTER_AREA,
        )
        s = sigma_px / step
        k = 2 * int(np.ceil(3 * s)) + 1
        small = cv2.GaussianBlur(small, (k, k), s, borderType=cv2.BORDER_CONSTANT)
        back = cv2.resize(small, (cols + pc, rows + pr), interpolation=cv2.INTER_LINEAR)
        return back[:rows, :cols]
    k = 2 * int(np.ceil(3 * sigma_px)) + 1
    return cv2.GaussianBlur(x, (k, k), sigma_px, borderType=cv2.BORDER_CONSTANT)


def _normalised(
    x: np.ndarray, w: np.ndarray, sigma_px: float, dens: dict | None = None
) -> np.ndarray:
    """Normalised convolution (Knutsson & Westin 1993): G*(w·x) / G*w, 0 where G*w ≈ 0.
    dens: a cache of G*w by σ for calls that share w."""
    if sigma_px <= 0:
        return np.where(w > 0, x, np.float32(0)).astype(np.float32, copy=False)
    num = _smooth((x * w).astype(np.float32, copy=False), sigma_px)
    den = None if dens is None else dens.get(sigma_px)
    if den is None:
        den = _smooth(w.astype(np.float32, copy=False), sigma_px)
        if dens is not None:
            dens[sigma_px] = den
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-4, num / den, np.float32(0)).astype(np.float32, copy=False)


def band_noise_gain(fine_px: float, coarse_px: float | None) -> float:
    """Σ (g_fine − g_coarse)²: the variance of unit white noise after the band filter (g_0 the
    identity, g_None zero), computed on the discrete kernels used here."""
    n = 2 * int(np.ceil(3 * (coarse_px or fine_px or 1))) + 33
    delta = np.zeros((n, n), np.float32)
    delta[n // 2, n // 2] = 1
    fine = delta if fine_px <= 0 else _smooth(delta, fine_px)
    coarse = np.zeros_like(delta) if coarse_px is None else _smooth(delta, coarse_px)
    return float(np.sum(np.square(fine.astype(np.float64) - coarse)))


def _bands(d, w, scales, dens=None):
    """The band images (finest first) of d weighted by w: differences of normalised blurs."""
    low = [_normalised(d, w, s, dens) for s in scales]
    return [low[i] - low[i + 1] for i in range(len(scales) - 1)] + [low[-1]]


def fringe_noise_colour(
    azimuth_heights_um: np.ndarray,
    azimuth_sigma_um: np.ndarray,
    mask: np.ndarray,
    *,
    scales_px: tuple[float, ...] = BAND_SCALES_PX,
    outlier_sigmas: float = 4.0,
    max_pairs: int = 3,
) -> np.ndarray:
    """κ per band: the fringe noise's band variance over what white noise of the predicted σ
    would give, measured on differences of azimuths (the surface and every error they share
    cancel). 1 = white; > 1 red (correlated over the band's scale).

    azimuth_heights_um, azimuth_sigma_um: (A, H, W), NaN where an azimuth has no height;
    mask: (H, W) bool. Pairs of consecutive azimuths (at most `max_pairs`), their
    differences beyond `outlier_sigmas`·σ left out (a wrong order, a shadow edge); on a
    central crop of at most 512 × 512 px of the mask's bounding box; per pair and band the
    median of band²/(σ_a² + σ_b²)/0.4549/c_b over pixels whose 5 × 5 neighbourhood is
    valid, then the median over pairs. Bands without data, or a single azimuth: κ = 1.
    """
    h = np.asarray(azimuth_heights_um, np.float32)
    sg = np.asarray(azimuth_sigma_um, np.float32)
    m = np.asarray(mask, bool)
    if h.ndim != 3 or sg.shape != h.shape or m.shape != h.shape[1:]:
        raise ValueError(
            f"azimuth heights {h.shape}, sigmas {sg.shape} and mask {m.shape} must agree"
        )
    n_bands = len(scales_px)
    out = np.ones(n_bands, np.float64)
    if h.shape[0] < 2 or not m.any():
        return out
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    rc, cc = (rows[0] + rows[-1]) // 2, (cols[0] + cols[-1]) // 2
    half = _COLOUR_CROP_PX // 2
    r0, c0 = max(rc - half, rows[0]), max(cc - half, cols[0])
    box = (slice(r0, min(r0 + 2 * half, rows[-1] + 1)), slice(c0, min(c0 + 2 * half, cols[-1] + 1)))
    gains = [
        band_noise_gain(scales_px[i], scales_px[i + 1] if i + 1 < n_bands else None)
        for i in range(n_bands)
    ]
    ratios: list[list[float]] = [[] for _ in range(n_bands)]
    pairs = [(a, a + 1) for a in range(h.shape[0] - 1)][:max_pairs]
    for a, b in pairs:
        ha, hb = h[a][box], h[b][box]
        var = np.square(sg[a][box]) + np.square(sg[b][box])
        diff = ha - hb
        with np.errstate(invalid="ignore"):
            ok = m[box] & np.isfinite(diff) & np.isfinite(var) & (var > 0)
            ok &= np.square(diff) <= outlier_sigmas**2 * var
        if ok.sum() < 400:
            continue
        w = ok.astype(np.float32)
        bands = _bands(np.where(ok, diff, 0).astype(np.float32), w, scales_px)
        core = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
        if core.sum() < 100:
            continue
        v = var[core]
        for i, band in enumerate(bands):
            r = float(fast_median(np.square(band[core]) / v)) / _CHI2_1_MEDIAN / gains[i]
            ratios[i].append(r)
    for i, r in enumerate(ratios):
        if r:
            out[i] = float(np.median(r))
    return out


def band_wiener_correct(
    height_um: np.ndarray,
    fringe_height_um: np.ndarray,
    mask: np.ndarray,
    *,
    noise_sigma_um: np.ndarray,
    crease_sigma_um: np.ndarray,
    colour: np.ndarray,
    blur_px: float = 0.0,
    resolution_px: float = 0.0,
    scales_px: tuple[float, ...] = BAND_SCALES_PX,
    outlier_sigmas: float = 3.0,
    window: float = 2.0,
) -> BandCorrection:
    """The fused heights moved toward the fringe heights by each band's local Wiener gain
    (module docstring).

    height_um: (H, W) fused heights, NaN off the mask; fringe_height_um: (H, W), NaN where
    none; mask: (H, W) bool. noise_sigma_um: (H, W) the fringe heights' phase noise
    (`Measurements.fringe_sigma_um`); crease_sigma_um: (H, W) their model error at bends
    (`quality.crease_sigma_um`); colour: κ per band (`fringe_noise_colour`); blur_px: the
    fringes' blur relative to the normals (`quality.fringe_blur_px`). resolution_px: σ of
    the fringe heights' whole blur relative to the surface's point samples (their blur
    relative to the normals, the camera's PSF and the pixel's area); a band whose finest
    scale is below it stands down: a Gaussian of σ keeps less than half of a detail of scale
    below σ (transfer s²/(s² + σ²) at the band's edge), so there the fringe heights hold
    little of the surface and their errors the azimuths share (pixel mixing, common phase
    errors), which κ cannot show. outlier_sigmas: the
    Cauchy scale of a band's disagreement, in units of its local RMS; fringe heights more
    than 4 (σ_ph + crease) from the fused surface are left out. window: the local mean's
    σ in units of the band's coarse scale. Pixels off the mask, or where h is NaN, are
    returned unchanged.
    """
    h = np.asarray(height_um, np.float32)
    f = np.asarray(fringe_height_um, np.float32)
    m = np.asarray(mask, bool)
    sn = np.asarray(noise_sigma_um, np.float32)
    cr = np.asarray(crease_sigma_um, np.float32)
    kappa = np.asarray(colour, np.float64)
    if not (h.shape == f.shape == m.shape == sn.shape == cr.shape):
        raise ValueError("height, fringe height, mask, noise and crease maps must have one shape")
    if kappa.shape != (len(scales_px),):
        raise ValueError(f"colour must have one value per band ({len(scales_px)})")
    if not resolution_px >= 0:
        raise ValueError(f"resolution_px must be >= 0, got {resolution_px}")
    n_bands = len(scales_px)
    out = h.copy()
    surface = m & np.isfinite(h)
    if surface.sum() < 100:
        return BandCorrection(out, (0.0,) * n_bands, (0.0,) * n_bands)
    # Only the surface's bounding box: every blur below weights the pixels off it by 0.
    rows, cols = np.flatnonzero(surface.any(axis=1)), np.flatnonzero(surface.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    corrected, gains, shares = _correct_box(
        h[box],
        f[box],
        surface[box],
        sn[box],
        cr[box],
        kappa,
        blur_px,
        resolution_px,
        scales_px,
        outlier_sigmas,
        window,
    )
    out[box] = corrected
    return BandCorrection(out, gains, shares)


def _correct_box(
    h, f, surface, sn, cr, kappa, blur_px, resolution_px, scales_px, outlier_sigmas, window
):
    """`band_wiener_correct` on a box holding the whole surface: (heights, gains, shares)."""
    n_bands = len(scales_px)
    with np.errstate(invalid="ignore"):
        valid = surface & np.isfinite(f) & np.isfinite(sn) & (sn > 0) & np.isfinite(cr)
    if valid.sum() < 100:
        return h, (0.0,) * n_bands, (0.0,) * n_bands
    # Compare like with like: the fused surface blurred as the fringes are.
    hs = np.where(surface, h, 0).astype(np.float32)
    hb = _normalised(hs, surface.astype(np.float32), blur_px) if blur_px > 0 else hs
    d = np.where(valid, f - hb, 0).astype(np.float32)
    with np.errstate(invalid="ignore"):
        valid &= np.square(d) <= 16 * np.square(sn + cr)
    # Zero where not valid: an inf σ times a zero weight would poison every blur with NaN.
    noise2 = np.where(valid, np.square(sn), 0).astype(np.float32)
    # A fringe height counts by how much of its error is noise rather than crease error.
    share = noise2 + np.square(np.where(valid, cr, 0))
    w = np.where(valid, noise2 / np.where(valid, share, 1), 0).astype(np.float32)
    d = np.where(valid, d, 0).astype(np.float32)
    dens: dict = {}  # G*w by σ, shared by every normalised blur below
    bands = _bands(d, w, scales_px, dens)
    correction = np.zeros(h.shape, np.float32)
    k2 = np.float32(outlier_sigmas**2)
    gains, shares = [], []
    n_mask = max(int(surface.sum()), 1)
    for i, band in enumerate(bands):
        if scales_px[i] < resolution_px:  # finer than the fringes resolve: left to the fusion
            gains.append(0.0)
            shares.append(0.0)
            continue
        coarse = scales_px[i + 1] if i + 1 < n_bands else None
        c = band_noise_gain(scales_px[i], coarse)
        local = coarse if coarse is not None else 2 * scales_px[i]
        v_f = np.float32(kappa[i] * c) * _normalised(noise2, w, max(local, 1.0), dens)
        energy = _normalised(np.square(band), w, window * local, dens)
        acts = surface & (energy > v_f)  # elsewhere the band stands down (and 0/0 is avoided)
        safe = np.where(acts, energy, np.float32(1))
        gain = np.where(acts, (1 - v_f / safe) / (1 + np.square(band) / (k2 * safe)), 0)
        gain = gain.astype(np.float32, copy=False)
        correction += gain * band
        gains.append(float(gain[surface].mean()))
        shares.append(float(np.count_nonzero(acts) / n_mask))
    out = np.where(surface, h + correction, h).astype(np.float32)
    return out, tuple(gains), tuple(shares)
