"""The plain chain: textbook photometric stereo, fringe heights and one fixed-weight fusion.

The floor every default reconstruction must clear (issue 14, "the plain chain as a choice"):
each step is the form found in the textbooks, with constants fixed here, the same for every
scan, and nothing estimated from the scan beyond what the formulas need.

1. Least-squares photometric stereo (Woodham 1980, "Photometric method for determining
   surface orientation from multiple images", Opt. Eng. 19(1)): per pixel, s_k = l_k·b with
   b = ρn, solved by least squares over the lit samples only: a sample below
   `SHADOW_FRACTION` of the pixel's brightest one is a shadow (cast or attached), a saturated
   one says nothing; at least 3 samples whose lights span 3-D are needed.
2. Fringe heights: 4-step phase per set (`recon.fringe.four_step_phase`), object minus
   reference phase, hierarchical temporal unwrapping coarse → fine (Huntley & Saldner 1993;
   Zuo et al. 2016, `recon.unwrap.temporal_unwrap`), h = −Δψ·P/(2π·tanθ), and the heights of
   the azimuths averaged (`average_azimuths_um`).
3. One screened-Poisson solve with fixed weights (`fuse_plain_um`):
   E(h) = Σ_edges (h_q − h_p − s·ḡ)² + λ·Σ_pixels (h_p − f_p)², λ = `fringe_weight(s)`, from
   two constant noise figures (`SLOPE_SIGMA`, `HEIGHT_SIGMA_UM`).

All functions are pure (arrays in, arrays out, inputs never modified); `worker.plain_chain`
reads the bundle and writes the model directory.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from worker.recon.integrate import (
    edge_targets_um,
    masked_edge_weights,
    slopes_from_normals,
    solve_screened_poisson,
)
from worker.recon.mask import otsu_threshold

__all__ = [
    "HEIGHT_SIGMA_UM",
    "MEMBRANE_WEIGHT",
    "MIN_ALBEDO",
    "MIN_MODULATION",
    "ORDER_RESIDUAL_MAX",
    "SHADOW_FRACTION",
    "SLOPE_SIGMA",
    "average_azimuths_um",
    "fringe_weight",
    "fuse_plain_um",
    "least_squares_normals",
    "normals_from_height",
    "plain_mask",
]

# A sample below this fraction of the pixel's brightest sample is taken for a shadow.
SHADOW_FRACTION = 0.1
# Fixed noise figures that weigh slopes against fringe heights, the same for every scan (the
# plain chain does not measure a scan's noise): a least-squares photometric normal is good to
# about 0.02 in slope (1.1°, with clay's gloss and shadows), a fringe height to about 2.5 µm.
# An edge's step s·ḡ then errs by s·0.02 µm, and the data weight relative to an edge is
# λ = (s·SLOPE_SIGMA / HEIGHT_SIGMA_UM)² (`fringe_weight`): 0.046 at 26.8 µm pixels, 0.33 at
# 71 µm, 1.3 at 143 µm. The screened Poisson equation −∇²h + λh = λf − ∇·g passes the fringe
# heights below the spatial frequency √λ rad/px and the normals above it.
SLOPE_SIGMA = 0.02
HEIGHT_SIGMA_UM = 2.5
# Edge weight of a masked pixel pair without a slope (no normal): a faint membrane (target 0)
# that makes such pixels follow their neighbours instead of floating free.
MEMBRANE_WEIGHT = 1e-3
# A level whose modulation (the smaller of object and reference) is below this does not
# refine a pixel (`temporal_unwrap`'s default); the coarsest level below it leaves the pixel
# without a height at that azimuth.
MIN_MODULATION = 0.15
# Pixels whose unwrapping prediction missed by more than this many fringe orders (0.5 is a
# coin toss) are dropped at that azimuth (Zuo et al. 2016's reliability criterion).
ORDER_RESIDUAL_MAX = 0.25
# Clay reflects 10-60 %; the mask never takes anything darker than this.
MIN_ALBEDO = 0.02


def fringe_weight(pixel_size_um: float) -> float:
    """λ = (s·SLOPE_SIGMA / HEIGHT_SIGMA_UM)²: a fringe height's weight relative to one edge's
    slope term, both as inverse variances in µm⁻² scaled alike (maximum likelihood for those
    fixed noise figures)."""
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    return float((pixel_size_um * SLOPE_SIGMA / HEIGHT_SIGMA_UM) ** 2)


def least_squares_normals(
    shading: np.ndarray,
    light_dirs: np.ndarray,
    *,
    saturated: np.ndarray | None = None,
    shadow_fraction: float = SHADOW_FRACTION,
    min_condition: float = 1e-3,
    block_px: int = 1 << 16,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Woodham's least-squares photometric stereo over the lit samples of each pixel.

    shading: (K, H, W) float, s_k = ρ·max(0, n·l_k) (flat-fielded, any common scale), NaN
    where unknown. light_dirs: (K, 3) unit vectors toward the sources (SCAN_BUNDLE.md).
    saturated: (K, H, W) bool, samples that reached the camera's full scale (left out).
    shadow_fraction: samples below this fraction of the pixel's brightest usable sample are
    shadows (left out). min_condition: the lit lights' normal matrix Σ l lᵀ must have
    det / (trace/3)³ at least this (they span 3-D).

    Returns normals (H, W, 3) float32 (unit, n_z < 0), albedo (H, W) float32 = |b| and the
    number of samples used (H, W) int16; NaN normals and albedo where fewer than 3 lit samples
    or a degenerate set of lights.
    """
    s = np.asarray(shading)
    lights = np.asarray(light_dirs, np.float64)
    if s.ndim != 3:
        raise ValueError(f"shading must have shape (K, H, W), got {s.shape}")
    k, rows, cols = s.shape
    if lights.shape != (k, 3):
        raise ValueError(f"light_dirs must have shape ({k}, 3), got {lights.shape}")
    if saturated is not None and np.shape(saturated) != s.shape:
        raise ValueError(f"saturated must have shape {s.shape}, got {np.shape(saturated)}")
    if not 0.0 <= shadow_fraction < 1.0:
        raise ValueError(f"shadow_fraction must lie in [0, 1), got {shadow_fraction}")
    n_px = rows * cols
    flat = s.reshape(k, n_px)
    sat = None if saturated is None else np.asarray(saturated, bool).reshape(k, n_px)
    normals = np.full((n_px, 3), np.nan, np.float32)
    albedo = np.full(n_px, np.nan, np.float32)
    used = np.zeros(n_px, np.int16)
    # The six distinct entries of l lᵀ per light (xx, xy, xz, yy, yz, zz).
    iu = np.triu_indices(3)
    ll6 = (lights[:, :, None] * lights[:, None, :])[:, iu[0], iu[1]]  # (K, 6)
    for p0 in range(0, n_px, block_px):
        p1 = min(p0 + block_px, n_px)
        sb = flat[:, p0:p1].astype(np.float64)
        ok = np.isfinite(sb)
        if sat is not None:
            ok &= ~sat[:, p0:p1]
        brightest = np.max(np.where(ok, sb, -np.inf), axis=0)
        ok &= sb > shadow_fraction * brightest
        ok &= sb > 0
        w = ok.astype(np.float64)
        m6 = w.T @ ll6  # (P, 6) Σ l lᵀ over the lit samples
        rhs = (np.where(ok, sb, 0.0)).T @ lights  # (P, 3) Σ s l
        m = np.empty((p1 - p0, 3, 3))
        m[:, iu[0], iu[1]] = m6
        m[:, iu[1], iu[0]] = m6
        count = ok.sum(axis=0)
        used[p0:p1] = count
        det = np.linalg.det(m)
        scale = np.trace(m, axis1=1, axis2=2) / 3.0
        with np.errstate(divide="ignore", invalid="ignore"):
            good = (count >= 3) & (det / np.maximum(scale, 1e-300) ** 3 >= min_condition)
        if not good.any():
            continue
        b = np.linalg.solve(m[good], rhs[good][:, :, None])[:, :, 0]
        rho = np.linalg.norm(b, axis=1)
        n = b / np.where(rho > 0, rho, np.nan)[:, None]
        # A normal facing away from the camera is not a surface it sees: clamp to n_z ≤ −1e-3.
        n[:, 2] = np.minimum(n[:, 2], -1e-3)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        idx = np.flatnonzero(good) + p0
        normals[idx] = n
        albedo[idx] = rho
    return normals.reshape(rows, cols, 3), albedo.reshape(rows, cols), used.reshape(rows, cols)


def average_azimuths_um(
    height_um: np.ndarray, *, outlier_um: float, min_azimuths: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the azimuths' fringe heights per pixel, after dropping wrong fringe orders.

    height_um: (A, H, W) µm, NaN where an azimuth has no height. outlier_um: an azimuth
    further than this from the per-pixel median of the azimuths is dropped; it should be a
    fraction of the finest period's height equivalent P/tanθ, the error of one wrong order
    (with two azimuths the median is their mean and both are kept or both dropped).
    min_azimuths: pixels with fewer azimuths left are NaN (one azimuth alone cannot show
    that its order is wrong: at the silhouette a pixel mixing tablet and support can pass
    every test of its own unwrapping with a height centimetres off).
    Returns the mean height (H, W) float32 (NaN where none is left) and the number of
    azimuths averaged (H, W) int16.
    """
    h = np.asarray(height_um, np.float32)
    if h.ndim != 3:
        raise ValueError(f"height_um must have shape (A, H, W), got {h.shape}")
    if not outlier_um > 0:
        raise ValueError(f"outlier_um must be > 0, got {outlier_um}")
    finite = np.isfinite(h)
    count = finite.sum(axis=0)
    med = np.full(h.shape[1:], np.nan, np.float32)
    any_ok = count > 0
    if any_ok.any():
        med[any_ok] = np.nanmedian(h[:, any_ok], axis=0)
    keep = finite & (np.abs(h - med) <= np.float32(outlier_um))
    n = keep.sum(axis=0)
    total = np.where(keep, h, 0).sum(axis=0)
    if min_azimuths < 1:
        raise ValueError(f"min_azimuths must be >= 1, got {min_azimuths}")
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n >= min_azimuths, total / np.maximum(n, 1), np.nan)
    return mean.astype(np.float32), np.where(n >= min_azimuths, n, 0).astype(np.int16)


def plain_mask(
    brightness: np.ndarray,
    measured: np.ndarray,
    *,
    min_albedo: float = MIN_ALBEDO,
    min_part_fraction: float = 0.2,
) -> np.ndarray:
    """The tablet: bright and measured pixels, by one rule for every scan.

    brightness: (H, W) albedo relative to white (or a quantity proportional to it), NaN
    where unknown. measured: (H, W) bool, pixels with a normal or a fringe height.
    Clay and a dark support differ by a factor, so Otsu's threshold (1979) is taken on log
    brightness, never below `min_albedo`; then the connected parts at least
    `min_part_fraction` of the largest, holes filled (wedge floors in shadow are tablet),
    one pixel eroded off the rim.
    """
    b = np.asarray(brightness, np.float32)
    m = np.asarray(measured, bool)
    if b.ndim != 2 or m.shape != b.shape:
        raise ValueError(f"brightness and measured must be (H, W) alike, got {b.shape}, {m.shape}")
    ok = np.isfinite(b) & (b > 0)
    if ok.sum() < 16:
        return np.zeros(b.shape, bool)
    try:
        t = float(np.exp(otsu_threshold(np.log(b[ok]))))
    except ValueError:
        t = 0.0
    fg = ok & (b > max(t, min_albedo)) & m
    labels, count = ndimage.label(fg)
    if count == 0:
        return fg
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    keep = np.concatenate([[False], sizes >= min_part_fraction * sizes.max()])
    fg = ndimage.binary_fill_holes(keep[labels])
    # The rim's pixels mix the tablet's side with the support far below: not measurements.
    return ndimage.binary_erosion(fg, structure=np.ones((3, 3), bool))


def fuse_plain_um(
    normals: np.ndarray | None,
    fringe_height_um: np.ndarray | None,
    mask: np.ndarray,
    *,
    pixel_size_um: float,
    data_weight: float | None = None,
    rtol: float = 1e-7,
) -> np.ndarray:
    """Heights (H, W) float32 µm from one screened-Poisson solve with fixed weights.

    E(h) = Σ_edges w_e (h_q − h_p − t_e)² + Σ_pixels λ_p (h_p − f_p)²: w_e = 1 on mask edges
    whose two pixels have a normal, t_e the trapezoid rule s·(g_p + g_q)/2 of their slopes
    g = (n_x/n_z, n_y/n_z); other mask edges with an end lacking a fringe height get the
    faint membrane `MEMBRANE_WEIGHT` with t = 0; λ_p = data_weight (default `fringe_weight(pixel_size_um)`) where the fringe height
    f_p is finite, else 0 (Simchony et al.
    1990 for the solver; Nehab et al. 2005 for combining positions and normals).
    normals: (H, W, 3) unit, n_z < 0, NaN allowed, or None (fringe-only bundle: the
    heights alone, holes filled by the membrane). fringe_height_um: (H, W) or None
    (photometric-only bundle: the normals integrated, mean height 0 per connected part).
    NaN off the mask and at mask pixels that nothing reaches. rtol: the solver's relative
    residual (strict: the membrane's faint terms barely show in it, and holes would be left
    half-filled; 1e-7 costs 23 rather than 16 iterations at 512×384).
    """
    m = np.asarray(mask, bool)
    if m.ndim != 2:
        raise ValueError(f"mask must be (H, W), got {m.shape}")
    if normals is None and fringe_height_um is None:
        raise ValueError("normals and fringe_height_um cannot both be None")
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    lam_f = fringe_weight(pixel_size_um) if data_weight is None else float(data_weight)
    if not lam_f > 0:
        raise ValueError(f"data_weight must be > 0, got {data_weight}")
    out = np.full(m.shape, np.nan, np.float32)
    if not m.any():
        return out
    if normals is not None:
        if np.shape(normals) != (*m.shape, 3):
            raise ValueError(f"normals must have shape {(*m.shape, 3)}, got {np.shape(normals)}")
        gx, gy = slopes_from_normals(normals, min_abs_nz=0.05)
        has_g = m & np.isfinite(gx) & np.isfinite(gy)
    else:
        gx = gy = np.zeros(m.shape, np.float32)
        has_g = np.zeros(m.shape, bool)
    tx, ty = edge_targets_um(
        np.where(has_g, gx, 0), np.where(has_g, gy, 0), pixel_size_um=pixel_size_um
    )
    lam = data = None
    has_f = np.zeros(m.shape, bool)
    if fringe_height_um is not None:
        f = np.asarray(fringe_height_um, np.float32)
        if f.shape != m.shape:
            raise ValueError(f"fringe_height_um must have shape {m.shape}, got {f.shape}")
        has_f = m & np.isfinite(f)
        lam = np.where(has_f, np.float32(lam_f), np.float32(0))
        data = np.where(has_f, f, np.float32(0))
    wx, wy = masked_edge_weights(m, np.where(has_g, np.float32(1), np.float32(MEMBRANE_WEIGHT)))
    # The membrane only where an end has no fringe height: between two measured heights it
    # would only flatten them.
    wx[(wx < 1) & has_f[:, 1:] & has_f[:, :-1]] = 0
    wy[(wy < 1) & has_f[1:, :] & has_f[:-1, :]] = 0
    sol = solve_screened_poisson(
        tx, ty, wx, wy, data_um=data, data_weight=lam, rtol=rtol, max_iter=5000
    )
    h = sol.height_um
    # Parts of the mask that neither a fringe height nor an edge reaches are not measured.
    labels, count = ndimage.label(m)
    reached = np.zeros(count + 1, bool)
    reached[np.unique(labels[has_f | has_g])] = True
    reached[0] = False
    linked = np.zeros(m.shape, bool)
    linked[:, 1:] |= wx > 0
    linked[:, :-1] |= wx > 0
    linked[1:, :] |= wy > 0
    linked[:-1, :] |= wy > 0
    valid = m & reached[labels] & (linked | has_f)
    if fringe_height_um is None:
        # Normals alone fix the shape up to a constant per part: mean height 0.
        lab, n = ndimage.label(valid)
        if n:
            sums = np.bincount(lab.ravel(), weights=np.where(valid, h, 0).ravel(), minlength=n + 1)
            cnt = np.bincount(lab.ravel(), minlength=n + 1)
            offset = (sums / np.maximum(cnt, 1)).astype(np.float32)
            offset[0] = 0
            h = h - offset[lab]
    out[valid] = h[valid]
    return out


def normals_from_height(height_um: np.ndarray, *, pixel_size_um: float) -> np.ndarray:
    """Unit normals (H, W, 3) float32 of the surface h by central differences (one-sided at
    the rim of the finite pixels), n ∝ (−∂h/∂x, −∂h/∂y, −1); NaN where h is NaN."""
    h = np.asarray(height_um, np.float64)
    if h.ndim != 2:
        raise ValueError(f"height_um must be (H, W), got {h.shape}")
    finite = np.isfinite(h)
    out = np.full((*h.shape, 3), np.nan, np.float32)
    if not finite.any():
        return out
    # Off-surface neighbours take the nearest surface value: one-sided slopes at the rim.
    idx = ndimage.distance_transform_edt(~finite, return_distances=False, return_indices=True)
    filled = h[tuple(idx)]
    gy, gx = np.gradient(filled, float(pixel_size_um))
    norm = np.sqrt(gx * gx + gy * gy + 1.0)
    for c, comp in enumerate((-gx, -gy, -np.ones_like(gx))):
        out[..., c] = np.where(finite, comp / norm, np.nan)
    return out
