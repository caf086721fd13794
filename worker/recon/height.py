"""Heights from unwrapped fringe phase, their robust combination over azimuths, hole filling.

Triangulation (SCAN_BUNDLE.md): relative to the reference plane the phase at p is shifted by
Δψ = −2π·h·tanθ/P, so h = −Δψ·P/(2π·tanθ) (the paper's height-from-phase relation for a
collimated source at polar angle θ and an orthographic camera).

What the fringe height measures: the pattern seen at p left the source along the ray that
meets the reference plane at p′ = p − h·tanθ·u, so the phase dates the surface point that the
ray from p′ hits first.  Near a steep wall facing away from the source, or inside a cast
shadow, the pixel sees no fringe at all (V = 0, modulation ≈ 0); on a wall facing the source
the fringe is compressed and blurred over the pixel, and interreflections add unmodulated or
wrongly phased light.  Those azimuths must get weight 0 (low modulation, shadow): every
pixel seen from at least one azimuth with good modulation is then measured directly, and
:func:`fill_holes` interpolates the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import scipy.ndimage as ndi

from worker.recon.arrays import copy_where, fast_median
from worker.recon.parallel import run_blocks

__all__ = [
    "GUARD_CLIFF",
    "GUARD_FRINGE",
    "GUARD_NEIGHBOURHOOD",
    "CombinedHeight",
    "GuardedHeight",
    "combine_azimuths",
    "consensus_azimuths",
    "fill_holes",
    "guard_heights",
    "valid_fringe",
    "height_from_phase",
]


@dataclass(frozen=True)
class CombinedHeight:
    """Output of :func:`combine_azimuths`.

    height_um : (H, W) float32, the weighted mean of the inlier azimuths; NaN where none.
    spread_um : (H, W) float32, weighted standard deviation of the inliers (0 with one).
    azimuths_used : (H, W) int16, number of inlier azimuths.
    sigma_um : (H, W) float32 or None, predicted σ of ``height_um`` from the inliers' σ
        (:func:`consensus_azimuths` only); NaN where ``height_um`` is.
    """

    height_um: np.ndarray
    spread_um: np.ndarray
    azimuths_used: np.ndarray
    sigma_um: np.ndarray | None = None


def height_from_phase(dpsi_rad: np.ndarray, *, period_um: float, polar_deg: float) -> np.ndarray:
    """h = −Δψ·P/(2π·tanθ) in µm, float32, same shape as ``dpsi_rad`` (unwrapped, rad)."""
    if not (np.isfinite(period_um) and period_um > 0):
        raise ValueError(f"period_um must be finite and > 0, got {period_um}")
    if not (0.0 < polar_deg < 90.0):
        raise ValueError(f"polar_deg must lie in (0, 90), got {polar_deg}")
    dpsi = np.asarray(dpsi_rad, dtype=np.float32)
    scale = np.float32(-period_um / (2.0 * np.pi * np.tan(np.deg2rad(polar_deg))))
    return dpsi * scale


def _weighted_median(values: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Per-column weighted median of (A, N) values; weight 0 or NaN values are ignored."""
    # Rows of A contiguous values sort far faster than strided columns.
    w = np.ascontiguousarray(np.where(np.isfinite(values), weight, 0.0).T)
    key = np.ascontiguousarray(np.where(w.T > 0, values, np.inf).T)
    order = np.argsort(key, axis=1)
    v = np.take_along_axis(key, order, axis=1)
    cw = np.cumsum(np.take_along_axis(w, order, axis=1), axis=1)
    total = cw[:, -1]
    idx = np.argmax(cw >= 0.5 * total[:, None], axis=1)
    med = np.take_along_axis(v, idx[:, None], axis=1)[:, 0]
    return np.where(total > 0, med, np.nan)


def _pooled_sigma(hf: np.ndarray, wf: np.ndarray) -> float:
    """Scan-wide σ of one azimuth's height from differences of azimuth pairs.

    For two independent N(0, σ²) errors |h_i − h_j| has median 0.6745·√2·σ; the median over
    every pixel and azimuth pair ignores up to half of corrupted pairs and, unlike the
    per-pixel MAD of a handful of azimuths, is not biased low.
    """
    diffs = []
    for i in range(hf.shape[0] - 1):
        both = (wf[i] > 0) & (wf[i + 1] > 0)
        diffs.append(np.abs(hf[i, both] - hf[i + 1, both]))
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    d = d[np.isfinite(d)]
    return float(np.median(d) / (0.6745 * np.sqrt(2.0))) if d.size else 0.0


def combine_azimuths(
    height_um: np.ndarray,
    weight: np.ndarray,
    *,
    k_sigma: float = 3.0,
    min_sigma_um: float | None = None,
) -> CombinedHeight:
    """Robust per-pixel combination of the heights of A azimuths.

    1. weighted median m over the azimuths with weight > 0 (shadowed or low-modulation
       azimuths should come with weight 0; NaN heights are ignored);
    2. robust scale σ = 1.4826·weighted median |h − m|, floored at ``min_sigma_um``;
    3. inliers |h − m| ≤ k_sigma·σ, result = their weighted mean.

    Parameters
    ----------
    height_um, weight : (A, H, W) float
        Heights (µm) and non-negative weights (e.g. modulation², or 1/σ_h²).
    min_sigma_um : float, optional
        Noise floor of σ (µm): with two or three azimuths the MAD can be 0.  When None it is
        estimated from the whole scan by :func:`_pooled_sigma`.
    """
    h = np.asarray(height_um, dtype=np.float32)
    w = np.asarray(weight, dtype=np.float32)
    if h.ndim != 3:
        raise ValueError(f"height_um must have shape (A, H, W), got {h.shape}")
    if w.shape != h.shape:
        raise ValueError(f"weight shape {w.shape} differs from height_um {h.shape}")
    if np.any(w < 0):
        raise ValueError("weight must be >= 0")
    if not k_sigma > 0:
        raise ValueError(f"k_sigma must be > 0, got {k_sigma}")
    if min_sigma_um is not None and not min_sigma_um >= 0:
        raise ValueError(f"min_sigma_um must be >= 0, got {min_sigma_um}")
    a, rows, cols = h.shape
    hf = h.reshape(a, -1)
    wf = np.where(np.isfinite(hf) & np.isfinite(w.reshape(a, -1)), w.reshape(a, -1), 0.0)
    med = _weighted_median(hf, wf)
    dev = np.abs(hf - med[None, :])
    sigma = 1.4826 * _weighted_median(dev, wf)
    if min_sigma_um is None:
        min_sigma_um = _pooled_sigma(hf, wf)
    scale = np.maximum(np.nan_to_num(sigma, nan=0.0), np.float32(min_sigma_um))
    inl = (wf > 0) & (dev <= k_sigma * scale[None, :])
    wi = np.where(inl, wf, 0.0)
    wsum = wi.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = (wi * np.nan_to_num(hf)).sum(axis=0) / wsum
        var = (wi * (np.nan_to_num(hf) - mean[None, :]) ** 2).sum(axis=0) / wsum
    solved = wsum > 0
    return CombinedHeight(
        height_um=np.where(solved, mean, np.nan).astype(np.float32).reshape(rows, cols),
        spread_um=np.where(solved, np.sqrt(np.maximum(var, 0.0)), np.nan)
        .astype(np.float32)
        .reshape(rows, cols),
        azimuths_used=inl.sum(axis=0).astype(np.int16).reshape(rows, cols),
    )


def _noise_scale(h: np.ndarray, s: np.ndarray, stride: int = 3) -> float:
    """Scan-wide factor by which the predicted σ understate the azimuths' disagreement.

    For a pair of azimuths with independent errors, z = (h_a − h_b)/√(σ_a² + σ_b²) is N(0, 1)
    if the σ are right; the median |z| over every pixel and pair is 0.6745·factor, robust to
    the pairs that are corrupted (those beyond |z| = 10 are left out first: a factor of 3
    would lose only 0.1 % of honest pairs there).  Model errors that the phase noise does not
    show (pixel mixing, blur on slopes, the pattern's harmonics) make the factor exceed 1;
    it is never taken below 1.
    """
    hs, ss = h[:, ::stride], s[:, ::stride]
    zs = []
    for i in range(h.shape[0]):
        for j in range(i + 1, h.shape[0]):
            with np.errstate(invalid="ignore"):
                z = np.abs(hs[i] - hs[j]) / np.sqrt(ss[i] ** 2 + ss[j] ** 2)
            # Gross disagreements (a wrong order is tens of σ) say nothing about the noise.
            zs.append(z[z < 10.0])
    z = np.concatenate(zs) if zs else np.zeros(0)
    return max(1.0, float(fast_median(z) / 0.6745)) if z.size >= 100 else 1.0


def consensus_azimuths(
    height_um: np.ndarray, sigma_um: np.ndarray, *, k_sigma: float = 4.0, workers: int = 1
) -> CombinedHeight:
    """Combine the heights of A azimuths by the largest mutually consistent group.

    Two azimuths agree at a pixel when |h_a − h_b| ≤ k·√(σ_a² + σ_b²), with the σ of each
    azimuth's height (from the unwrapping) scaled by the scan-wide factor of
    :func:`_noise_scale`.  Each azimuth in turn is a candidate centre; the one that the most
    azimuths agree with wins (ties: the largest total inverse variance), and the result is
    the inverse-variance weighted mean of the azimuths agreeing with it.  So a minority
    azimuth off by a fringe order (an unwrapping error) is dropped however precise it
    claims to be, which the weighted median of :func:`combine_azimuths` does not ensure.
    Two or more azimuths of which none agrees with another give NaN: no majority can say
    which is right (:func:`fill_holes` or the fusion takes over).  A single azimuth is taken
    as it is.

    height_um, sigma_um : (A, H, W); NaN height or non-finite σ: azimuth absent there.
    Returns :class:`CombinedHeight`; ``spread_um`` is the weighted SD of the inliers,
    ``sigma_um`` the σ of their mean, (Σ 1/σ_a²)^−½ with the scaled σ.
    workers: threads sharing the blocks of pixels (the result does not depend on it).
    """
    h = np.asarray(height_um, dtype=np.float32)
    s = np.asarray(sigma_um, dtype=np.float32)
    if h.ndim != 3:
        raise ValueError(f"height_um must have shape (A, H, W), got {h.shape}")
    if s.shape != h.shape:
        raise ValueError(f"sigma_um shape {s.shape} differs from height_um {h.shape}")
    if not k_sigma > 0:
        raise ValueError(f"k_sigma must be > 0, got {k_sigma}")
    a, rows, cols = h.shape
    hf = h.reshape(a, -1)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(hf) & np.isfinite(s.reshape(a, -1)) & (s.reshape(a, -1) > 0)
    sf = np.where(valid, s.reshape(a, -1), np.float32(np.inf))
    sf = sf * np.float32(_noise_scale(np.where(valid, hf, np.nan), sf))
    k2 = np.float32(k_sigma * k_sigma)
    n_pix = hf.shape[1]
    mean = np.empty(n_pix, np.float32)
    spread = np.empty(n_pix, np.float32)
    used = np.empty(n_pix, np.int16)
    sigma = np.empty(n_pix, np.float32)

    def combine(start: int) -> None:
        sl = slice(start, min(n_pix, start + _CONSENSUS_BLOCK))
        out = _consensus_block(hf[:, sl], sf[:, sl], valid[:, sl], k2)
        mean[sl], spread[sl], used[sl], sigma[sl] = out

    # Pixels are independent: blocks that fit the CPU cache, shared out between threads.
    run_blocks(combine, range(0, n_pix, _CONSENSUS_BLOCK), workers=workers)
    return CombinedHeight(
        height_um=mean.reshape(rows, cols),
        spread_um=spread.reshape(rows, cols),
        azimuths_used=used.reshape(rows, cols),
        sigma_um=sigma.reshape(rows, cols),
    )


_CONSENSUS_BLOCK = 1 << 16


def _consensus_block(hf, sf, valid, k2):
    """:func:`consensus_azimuths` on (A, n) pixels; returns mean, spread, used, sigma (n,)."""
    a, n_pix = hf.shape
    hv = np.where(valid, hf, np.float32(0))
    sf2 = np.square(sf)  # once, not per candidate centre
    wv = np.where(valid, np.float32(1) / sf2, np.float32(0))
    # agree[c][d]: azimuths c and d agree.  The test is symmetric to the bit (the same
    # square of ±(h_d − h_c), the same sum σ_c² + σ_d²), so each pair is tested once, and
    # an azimuth agrees with itself where it is valid (0 ≤ k²·2σ², σ² ≥ 0 or ∞).
    agree = [[valid[c] if c == d else None for d in range(a)] for c in range(a)]
    with np.errstate(invalid="ignore", over="ignore"):
        for c in range(a):
            for d in range(c + 1, a):
                diff2 = np.subtract(hv[d], hv[c])
                np.square(diff2, out=diff2)
                limit = np.add(sf2[d], sf2[c])
                limit *= k2
                pair = np.less_equal(diff2, limit)
                pair &= valid[c]
                pair &= valid[d]
                agree[c][d] = agree[d][c] = pair
    best_n = np.zeros(n_pix, dtype=np.int16)
    best_w = np.zeros(n_pix, dtype=np.float32)
    best = np.full(n_pix, -1, dtype=np.int16)
    for c in range(a):
        n = np.zeros(n_pix, dtype=np.int16)
        for d in range(a):
            n += agree[c][d]
        # Σ_d wv_d·agree_cd in the order of the (A, n) sum over axis 0, so the same bits.
        wsum = wv[0] * agree[c][0]
        for d in range(1, a):
            wsum += wv[d] * agree[c][d]
        better = (n > best_n) | ((n == best_n) & (wsum > best_w))
        copy_where(best_n, n, better)
        copy_where(best_w, wsum, better)
        copy_where(best, np.full_like(best, c), better)
    n_valid = valid.view(np.uint8).sum(axis=0, dtype=np.uint8)  # A < 256
    solved = (best >= 0) & ((best_n >= 2) | (n_valid == 1))
    # The inliers are the azimuths that agree with the chosen centre (a valid azimuth:
    # one that agrees with none never wins), picked row by row.
    inl = np.zeros((a, n_pix), dtype=bool)
    for c in range(a):
        chosen = best == c
        for d in range(a):
            copy_where(inl[d], agree[c][d], chosen)
    inl &= solved[None]
    wi = np.zeros_like(wv)
    copy_where(wi, wv, inl)
    wsum = wi.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = (wi * hv).sum(axis=0) / wsum
        var = (wi * np.square(hv - mean[None])).sum(axis=0) / wsum
        sigma = np.where(solved, np.float32(1) / np.sqrt(wsum), np.float32(np.nan))
    return (
        np.where(solved, mean, np.nan).astype(np.float32),
        np.where(solved, np.sqrt(np.maximum(var, 0.0)), np.nan).astype(np.float32),
        inl.sum(axis=0).astype(np.int16),
        sigma.astype(np.float32),
    )


def fill_holes(height: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Harmonic (Laplace) fill of the NaN pixels inside ``mask``.

    Every NaN pixel of ``mask`` that is connected (4-neighbourhood, through other such pixels)
    to a finite pixel gets the value that makes the discrete Laplacian vanish, with the finite
    pixels as Dirichlet boundary and no flux across pixels that are neither (Neumann): the
    smoothest surface through the hole's rim, solved as one sparse linear system.  Holes
    without any finite neighbour stay NaN; pixels outside ``mask`` are returned unchanged.

    height : (H, W) float; mask : (H, W) bool.  Returns (H, W) float32 (a new array).
    """
    z = np.asarray(height, dtype=np.float32)
    m = np.asarray(mask)
    if z.ndim != 2:
        raise ValueError(f"height must be 2-D, got shape {z.shape}")
    if m.shape != z.shape or m.dtype != bool:
        raise ValueError(f"mask must be a bool array of shape {z.shape}")
    out = z.copy()
    known = np.isfinite(z)
    hole = m & ~known
    if not hole.any() or not known.any():
        return out
    labels, n = ndi.label(hole)
    touching = np.unique(labels[ndi.binary_dilation(known) & hole])
    solvable = np.isin(labels, touching[touching > 0])
    if not solvable.any():
        return out
    idx = -np.ones(z.shape, dtype=np.int64)
    idx[solvable] = np.arange(int(solvable.sum()))
    nu = int(solvable.sum())
    rows_l, cols_l, vals_l = [], [], []
    diag = np.zeros(nu)
    rhs = np.zeros(nu)
    zz = np.where(known, z, 0.0).astype(np.float64)
    pad_idx = np.pad(idx, 1, constant_values=-1)
    pad_known = np.pad(known, 1, constant_values=False)
    pad_val = np.pad(zz, 1)
    h, w = z.shape
    i_all = idx[solvable]
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        win = (slice(1 + dr, 1 + dr + h), slice(1 + dc, 1 + dc + w))
        nb_idx = pad_idx[win][solvable]
        nb_known = pad_known[win][solvable]
        with_unknown = nb_idx >= 0
        rows_l.append(i_all[with_unknown])
        cols_l.append(nb_idx[with_unknown])
        vals_l.append(-np.ones(int(with_unknown.sum())))
        # Each neighbour that takes part adds 1 to the diagonal; a known one moves to the rhs.
        diag += with_unknown | nb_known
        rhs += np.where(nb_known, pad_val[win][solvable], 0.0)
    rows_l.append(np.arange(nu))
    cols_l.append(np.arange(nu))
    vals_l.append(diag)
    # Imported here: scipy.sparse.linalg (with scipy.linalg, 112 modules) costs ~0.1–0.2 CPU s
    # of every reconstruction's start-up, and most scans never reach this solve.
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    a = sp.csr_matrix(
        (np.concatenate(vals_l), (np.concatenate(rows_l), np.concatenate(cols_l))),
        shape=(nu, nu),
    )
    out[solvable] = spla.spsolve(a.tocsc(), rhs).astype(np.float32)
    return out


class GuardedHeight(NamedTuple):
    """Output of :func:`guard_heights`.

    height_um : (H, W) float32, the heights with every unsupported value replaced.
    flag : (H, W) uint8, 0 kept, 1 beyond the fringe bound, 2 outside its neighbourhood's
        range (no fringe height there); the pixels replaced (3, `GUARD_CLIFF`, is the
        pipeline's: a cliff pixel left NaN).
    """

    height_um: np.ndarray
    flag: np.ndarray


GUARD_FRINGE = 1
GUARD_NEIGHBOURHOOD = 2
# Set by the pipeline (`walls.unmeasured_jumps`): next to a cliff, no measurement told
# which side the pixel's centre is on; the height is left NaN.
GUARD_CLIFF = 3


def guard_heights(
    height_um: np.ndarray,
    fringe_height_um: np.ndarray,
    fringe_sigma_um: np.ndarray | None,
    mask: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    k_sigma: float = 5.0,
    floor_um: float = 50.0,
    radius: int = 3,
    pixel_size_um: float | None = None,
    max_slope: float = float(np.tan(np.radians(80.0))),
) -> GuardedHeight:
    """No height that the measurements do not support (SCAN_BUNDLE.md: a spike is worse
    than a hole).

    Where a fringe height f with σ exists, h must lie within f ± max(k_sigma·σ, floor_um)
    (σ NaN or missing: the floor alone). Elsewhere on the mask (no valid fringe height:
    shadowed for every azimuth, a chip floor, the mask's rim) h must lie within [min, max]
    of the fringe-bounded heights in its (2·radius + 1)² window, the window doubled (up to 4
    times) until it holds one, else of all of them; widened, when `pixel_size_um` is given,
    by what ground of slope `max_slope` (80°: a tablet's side, a chip's wall) rises over
    the distance d px to the nearest such height, d·s·max_slope (the side of the tablet
    at its silhouette falls below every interior neighbour; a spike of centimetres does not
    fit any surface). A pixel that breaks its rule is filled from its neighbourhood (the
    mean of the pixels around it that keep theirs, `_replace`) and the fill clipped to the
    bound, so no output pixel breaks it. NaN heights stay NaN; off the mask unchanged.

    height_um, fringe_height_um: (H, W) µm; fringe_sigma_um: (H, W) µm or None; mask bool;
    valid: (H, W) bool, the fringe heights that count as measurements (`valid_fringe`;
    None: every finite one).
    """
    h = np.asarray(height_um, np.float32)
    f = np.asarray(fringe_height_um, np.float32)
    m = np.asarray(mask, bool)
    if f.shape != h.shape or m.shape != h.shape:
        raise ValueError(f"fringe_height_um {f.shape} and mask {m.shape} must match {h.shape}")
    if not floor_um > 0 or not k_sigma > 0:
        raise ValueError("k_sigma and floor_um must be > 0")
    tol = np.full(h.shape, np.float32(floor_um))
    if fringe_sigma_um is not None:
        sig = np.asarray(fringe_sigma_um, np.float32)
        with np.errstate(invalid="ignore"):
            tol = np.fmax(tol, np.float32(k_sigma) * sig)
    here = m & np.isfinite(h)
    has_f = here & np.isfinite(f)
    if valid is not None:
        has_f &= np.asarray(valid, bool)
    with np.errstate(invalid="ignore"):
        lo = np.where(has_f, f - tol, np.nan).astype(np.float32)
        hi = np.where(has_f, f + tol, np.nan).astype(np.float32)
        bad_f = has_f & ((h < lo) | (h > hi))
    flag = np.zeros(h.shape, np.uint8)
    flag[bad_f] = GUARD_FRINGE
    # First the fringe-bounded pixels, then the others against their final values.
    out = _replace(h, bad_f, here, lo, hi)
    rest = here & ~has_f
    if not rest.any() or not has_f.any():
        return GuardedHeight(out, flag)
    n_lo, n_hi = _neighbourhood_range(np.where(has_f, out, np.nan), has_f, rest, radius)
    if pixel_size_um is not None:
        d = cv2.distanceTransform((~has_f).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        reach = d * np.float32(pixel_size_um * max_slope)
        n_lo, n_hi = n_lo - reach, n_hi + reach
    with np.errstate(invalid="ignore"):
        bad_n = rest & ((out < n_lo) | (out > n_hi))
    flag[bad_n] = GUARD_NEIGHBOURHOOD
    return GuardedHeight(_replace(out, bad_n, here, n_lo, n_hi), flag)


def _replace(h, bad, here, lo, hi):
    """h with the `bad` pixels filled from their neighbourhood and clipped to [lo, hi]: the
    mean of the pixels of `here` that keep theirs in a 3×3 window, widened (5, 9, 17, 33)
    where it holds none (window sums from two integral images, read at the bad pixels
    only); a pixel with none within 16 px takes its nearest bound."""
    out = h.copy()
    if not bad.any():
        return out
    keep = here & ~bad
    sums = cv2.integral(np.where(keep, h, np.float32(0)).astype(np.float64))
    counts = cv2.integral(keep.astype(np.uint8))
    rows, cols = np.nonzero(bad)
    fill = np.full(rows.size, np.nan)
    todo = np.ones(rows.size, bool)
    rmax, cmax = h.shape
    for half in (1, 2, 4, 8, 16):
        if not todo.any():
            break
        r0, r1 = np.clip(rows - half, 0, rmax), np.clip(rows + half + 1, 0, rmax)
        c0, c1 = np.clip(cols - half, 0, cmax), np.clip(cols + half + 1, 0, cmax)

        def window(t, r0=r0, r1=r1, c0=c0, c1=c1):
            return t[r1, c1] - t[r0, c1] - t[r1, c0] + t[r0, c0]

        n = window(counts).astype(np.float64)
        got = todo & (n > 0)
        fill[got] = window(sums)[got] / n[got]
        todo &= ~got
    lo_b, hi_b = lo[rows, cols], hi[rows, cols]
    value = np.where(np.isfinite(fill), fill, h[rows, cols])
    with np.errstate(invalid="ignore"):
        out[rows, cols] = np.clip(value, lo_b, hi_b)
    return out


def valid_fringe(
    fringe_height_um: np.ndarray,
    mask: np.ndarray,
    *,
    azimuths_used: np.ndarray | None,
    pixel_size_um: float,
    max_slope: float = float(np.tan(np.radians(60.0))),
    tolerance_um: float = 50.0,
) -> np.ndarray:
    """Fringe heights that a guard may hold a surface to: (H, W) bool.

    A fringe height is a measurement where it could be checked and passed: more than one
    azimuth agreed on it (`consensus_azimuths`; one azimuth has no cross-check), it lies at
    least two pixels inside the mask (a rim pixel mixes the tablet's side with the support
    below, and every azimuth then agrees on a wrong mixed phase), and it is within
    `tolerance_um` + 2·s·max_slope of the 5×5 median of the fringe heights (what ground the
    normals call continuous rises over two pixels: a lone wrong order or a mixed pixel at
    a cliff fails it), and the fringe heights of its 3×3 neighbours span no more than that
    (near a cliff a wrong side's height passes the median test). The others are bounded by
    their neighbourhood instead.
    """
    f = np.asarray(fringe_height_um, np.float32)
    m = np.asarray(mask, bool)
    ok = m & np.isfinite(f)
    if azimuths_used is not None:
        ok &= np.asarray(azimuths_used) >= 2
    inside = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
    ok &= inside
    if not ok.any():
        return ok
    fill = float(fast_median(f[ok]))
    # ndimage.median_filter(size=5) by OpenCV (float32 supports 5×5), ~40× faster.
    padded = np.pad(np.where(np.isfinite(f) & m, f, np.float32(fill)), 2, mode="edge")
    med = cv2.medianBlur(padded.astype(np.float32), 5)[2:-2, 2:-2]
    reach = np.float32(tolerance_um + 2 * pixel_size_um * max_slope)
    with np.errstate(invalid="ignore"):
        ok &= np.abs(f - med) <= reach
    # At a cliff the lower side's pixels next to the wall may report the upper side (the
    # projector's shadow and the camera's blur leave one or two azimuths, which agree on a
    # mixed phase) and pass the tests above: near a cliff no single fringe height tells
    # which side a pixel lies on. A height counts only where the fringe heights of its 3×3
    # neighbours on the mask, whether they passed or not, span no more than ground of slope
    # `max_slope` rises over two pixels; near a cliff (or next to a lone wrong order) the
    # neighbourhood bound applies instead (hard noise, 512×384: the fringe bound held ~50
    # px per scan to the wrong side, core RMS 10.8 → 13.9 µm).
    three = np.ones((3, 3), np.uint8)
    seen = m & np.isfinite(f)
    lo = cv2.erode(
        np.where(seen, f, np.float32(np.inf)),
        three,
        borderType=cv2.BORDER_CONSTANT,
        borderValue=np.inf,
    )
    hi = cv2.dilate(
        np.where(seen, f, np.float32(-np.inf)),
        three,
        borderType=cv2.BORDER_CONSTANT,
        borderValue=-np.inf,
    )
    ok &= (hi - lo) <= reach
    return ok


def _neighbourhood_range(values, known, where, radius):
    """Per pixel of `where`, (min, max) of `values` at `known` pixels in a window of
    2·radius + 1, doubled up to 4 times where it holds none, else the global range."""
    lo = np.full(values.shape, np.nan, np.float32)
    hi = np.full(values.shape, np.nan, np.float32)
    todo = where.copy()
    v_lo = np.where(known, values, np.inf).astype(np.float32)
    v_hi = np.where(known, values, -np.inf).astype(np.float32)
    r = radius
    for _ in range(5):
        if not todo.any():
            break
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        # Minimum and maximum filters (ndimage's, outside the image ignored) by OpenCV.
        w_lo = cv2.erode(v_lo, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        w_hi = cv2.dilate(v_hi, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
        got = todo & np.isfinite(w_lo)
        lo[got], hi[got] = w_lo[got], w_hi[got]
        todo &= ~got
        r *= 2
    if todo.any() and known.any():
        lo[todo], hi[todo] = float(values[known].min()), float(values[known].max())
    return lo, hi
