"""Heights of pixels that straddle a cliff, from the fringe mixture of its two sides.

A camera pixel integrates its footprint (SCAN_BUNDLE.md, "What a pixel measures"). Where a
vertical wall (a chip's cliff, an occluding edge) crosses the footprint, the complex fringe
response of period P relative to the reference target is a mixture of the two sides,

    Z(P) = a_hi·exp(−2πi·h_hi·tanθ/P) + a_lo·exp(−2πi·h_lo·tanθ/P),

with h_hi, h_lo the heights of the upper and lower side at the pixel (extrapolated from the
pure pixels around it) and a_hi, a_lo real: each side's brightness ρ·E·V·max(0, n·l) times
its share of the (blurred) footprint. Given the heights the model is linear in (a_hi, a_lo),
so least squares over the periods of one azimuth gives both (:func:`mixture_amplitudes`).
Divided by the amplitude of a pure pixel of the same side in the same azimuth
(:func:`own_amplitude`) each is that side's share of the footprint; an azimuth in which one
side lies in the projector's shadow (V = 0) still gives the other side's share. The
shares are those of the footprint blurred by the camera's PSF; :func:`deblur_fractions`
undoes a Gaussian PSF of σ px with the 3×3 kernel of the same variance (weights σ²/2 on
each side along each axis) to give the share of the pixel's own area, f. The area-mean
height that a real pixel integrates (and the simulator's ground truth) is then
f·h_hi + (1 − f)·h_lo (:func:`refine_cliff_heights`). Neither the normals (a vertical
wall shows no area) nor a single fringe phase (it lands on one side, or between) carries f.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage

__all__ = [
    "CliffRefinement",
    "CliffSamples",
    "RegionCheck",
    "UnmeasuredJumps",
    "check_refinement",
    "cliff_band",
    "cliff_samples",
    "deblur_fractions",
    "mixture_amplitudes",
    "own_amplitude",
    "refine_cliff_heights",
    "refine_cliffs",
    "side_heights",
    "unmeasured_jumps",
]

_OFFSETS8 = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]


@dataclass(frozen=True)
class CliffSamples:
    """One azimuth's per-period fringe response at a set of pixels.

    flat_index : (N,) int, sorted row-major pixel indices.
    amplitude : (L, N) float32, B_obj/B_ref, the 4-step amplitudes' ratio, per period.
    phase_rad : (L, N) float32, ψ_obj − ψ_ref (wrapped or not), per period.
    period_um : (L,) periods; tan_theta : tan of the polar angle.
    The complex response is Z = amplitude·exp(i·phase_rad).
    """

    flat_index: np.ndarray
    amplitude: np.ndarray
    phase_rad: np.ndarray
    period_um: np.ndarray
    tan_theta: float

    def response(self, pos: np.ndarray) -> np.ndarray:
        """Z (L, len(pos)) complex128 at positions ``pos`` of ``flat_index``."""
        return self.amplitude[:, pos] * np.exp(1j * self.phase_rad[:, pos].astype(np.float64))


def cliff_samples(
    height_um: np.ndarray,
    phase_rad: np.ndarray,
    amplitude_obj: list[np.ndarray],
    amplitude_ref: list[np.ndarray],
    *,
    period_um: np.ndarray,
    polar_deg: float,
    pixel_size_um: float,
    radius: int = 10,
    min_period_px: float = 4.0,
) -> CliffSamples:
    """One azimuth's fringe response kept where a cliff may be (for :func:`refine_cliff_heights`).

    Where: within ``radius`` px of a jump of this azimuth's heights beyond what ground of
    69° rises over one pixel (2.6 pixel sizes) or of the edge of its measured pixels (a
    cliff's shadow). That covers the pixels next to a cliff of the combined heights and
    the windows their sides are read from, without keeping 2·L floats per pixel of the
    whole frame. Periods under ``min_period_px`` pixels are left out: there a pixel
    averages the fringe away (aliasing under 2 px) and the fringe's carrier turns by
    more than π/4 over one side's part of a pixel, which the real shares of the mixture
    model ignore. height_um (H, W) NaN where not measured; phase_rad (L, H, W) object −
    reference phase; amplitude_obj/ref: L arrays (H, W) of 4-step amplitudes B.
    """
    h = np.asarray(height_um, np.float32)
    fin = np.isfinite(h)
    seed = np.zeros(h.shape, np.uint8)
    jump = np.float32(2.6 * pixel_size_um)
    with np.errstate(invalid="ignore"):
        dx = np.abs(np.diff(h, axis=1)) > jump
        dy = np.abs(np.diff(h, axis=0)) > jump
    dx |= fin[:, 1:] != fin[:, :-1]
    dy |= fin[1:] != fin[:-1]
    seed[:, 1:] |= dx
    seed[:, :-1] |= dx
    seed[1:] |= dy
    seed[:-1] |= dy
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    idx = np.flatnonzero(cv2.dilate(seed, k))
    periods = np.asarray(period_um, np.float64)
    use = np.flatnonzero(periods >= min_period_px * pixel_size_um)
    amp = np.empty((use.size, idx.size), np.float32)
    ph = np.empty((use.size, idx.size), np.float32)
    flat_phase = np.asarray(phase_rad).reshape(periods.size, -1)
    for j, i in enumerate(use):
        with np.errstate(invalid="ignore", divide="ignore"):
            amp[j] = amplitude_obj[i].ravel()[idx] / amplitude_ref[i].ravel()[idx]
        ph[j] = flat_phase[i, idx]
    return CliffSamples(
        flat_index=idx,
        amplitude=amp,
        phase_rad=ph,
        period_um=periods[use],
        tan_theta=float(np.tan(np.radians(polar_deg))),
    )


class CliffRefinement(NamedTuple):
    """Output of :func:`refine_cliff_heights`, (H, W) float32 each.

    height_um: the heights, refined at cliffs; fraction: f, the share of the pixel's area
    on the upper side; upper_um, lower_um: the two sides' heights at the pixel. NaN where
    not refined.
    """

    height_um: np.ndarray
    fraction: np.ndarray
    upper_um: np.ndarray
    lower_um: np.ndarray


def cliff_band(
    height_um: np.ndarray,
    mask: np.ndarray,
    *,
    min_jump_um: float,
    pixel_size_um: float,
    normals: np.ndarray | None = None,
    max_slope_deg: float = 60.0,
) -> np.ndarray:
    """Pixels with a 4-neighbour whose height differs by more than the ground can rise.

    A jump counts when |Δh| exceeds ``min_jump_um`` beyond what the two pixels' normals
    predict (their mean slope along the pair, clipped to ``max_slope_deg``: a cliff's
    straddling pixels have blended or shadow-spoilt normals that may claim any slope).
    NaN heights or pixels off the mask never form a jump. Returns (H, W) bool.
    """
    h = np.where(mask, np.asarray(height_um, np.float32), np.float32(np.nan))
    s = np.float32(pixel_size_um)
    cap = np.float32(np.tan(np.radians(max_slope_deg)))
    band = np.zeros(h.shape, bool)
    for axis, comp in ((1, 0), (0, 1)):
        d = np.diff(h, axis=axis)
        if normals is not None:
            n = np.asarray(normals, np.float32)
            with np.errstate(invalid="ignore", divide="ignore"):
                g = np.clip(np.nan_to_num(n[..., comp] / n[..., 2]), -cap, cap)
            gm = 0.5 * (g[:, 1:] + g[:, :-1]) if axis == 1 else 0.5 * (g[1:] + g[:-1])
            d = d - s * gm
        with np.errstate(invalid="ignore"):
            j = np.abs(d) > min_jump_um
        if axis == 1:
            band[:, 1:] |= j
            band[:, :-1] |= j
        else:
            band[1:] |= j
            band[:-1] |= j
    return band & mask


def side_heights(
    height_um: np.ndarray,
    normals: np.ndarray,
    pure: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    *,
    pixel_size_um: float,
    min_gap_um: float,
    radius: int = 5,
    min_count: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Heights of the upper and lower side at each pixel (rows, cols), and which are valid.

    Every ``pure`` pixel q of the (2·radius + 1)² window predicts the height at p from its
    own height and normal, h_q + ∇h_q·(p − q) (first-order Taylor). Sorted, the predictions
    of a pixel next to a cliff fall into two groups separated by the cliff; the largest gap
    between consecutive predictions splits them, and it must exceed ``min_gap_um`` with at
    least ``min_count`` predictions on each side. Each side's height is the median of its
    group weighted by 1/distance² (robust to a wedge or an outlier among the neighbours).
    A first pass over every other window pixel (a quarter of the work) drops the pixels
    with no such gap (steep ground is most of them).
    Returns h_hi, h_lo (N,) float64 and valid (N,) bool.
    """
    h = np.asarray(height_um)
    n = np.asarray(normals)
    rows = np.asarray(rows, np.intp)
    cols = np.asarray(cols, np.intp)
    with np.errstate(invalid="ignore"):
        usable = pure & np.isfinite(h) & (n[..., 2] < 0) & np.isfinite(n[..., 0] + n[..., 1])
    grid = (h, n, usable, float(pixel_size_um))
    coarse = [
        (dr, dc) for dr in range(-radius, radius + 1, 2) for dc in range(-radius, radius + 1, 2)
    ]
    coarse = [o for o in coarse if o != (0, 0)]
    _, _, maybe = _split_sides(grid, rows, cols, coarse, min_gap_um, max(2, min_count - 1))
    full = [(dr, dc) for dr in range(-radius, radius + 1) for dc in range(-radius, radius + 1)]
    full = [o for o in full if o != (0, 0)]
    h_hi = np.full(rows.size, np.nan)
    h_lo = np.full(rows.size, np.nan)
    valid = np.zeros(rows.size, bool)
    if maybe.any():
        hi, lo, ok = _split_sides(grid, rows[maybe], cols[maybe], full, min_gap_um, min_count)
        h_hi[maybe], h_lo[maybe], valid[maybe] = hi, lo, ok
    return h_hi, h_lo, valid


def _split_sides(grid, rows, cols, offsets, min_gap_um, min_count):
    """:func:`side_heights` over the given window offsets."""
    h, n, usable, s = grid
    rr, cc = h.shape
    k = len(offsets)
    pred = np.full((rows.size, k), np.inf)
    wgt = np.zeros((rows.size, k))
    for i, (dr, dc) in enumerate(offsets):
        qr, qc = rows + dr, cols + dc
        inside = (qr >= 0) & (qr < rr) & (qc >= 0) & (qc < cc)
        qr, qc = np.clip(qr, 0, rr - 1), np.clip(qc, 0, cc - 1)
        ok = inside & usable[qr, qc]
        nq = n[qr, qc].astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            p = h[qr, qc] - s * (nq[:, 0] * dc + nq[:, 1] * dr) / nq[:, 2]
        pred[:, i] = np.where(ok, p, np.inf)
        wgt[:, i] = np.where(ok, 1.0 / (dr * dr + dc * dc), 0.0)
    order = np.argsort(pred, axis=1)
    ps = np.take_along_axis(pred, order, axis=1)
    ws = np.take_along_axis(wgt, order, axis=1)
    count = np.isfinite(ps).sum(axis=1)
    with np.errstate(invalid="ignore"):
        gaps = np.diff(ps, axis=1)
    j = np.arange(k - 1)[None, :]
    # Only gaps that leave min_count predictions on either side can be the cliff.
    allowed = (j + 1 >= min_count) & (j + 1 <= count[:, None] - min_count)
    gaps = np.where(allowed & np.isfinite(gaps), gaps, -np.inf)
    split = np.argmax(gaps, axis=1)
    gap = np.take_along_axis(gaps, split[:, None], axis=1)[:, 0]
    valid = gap > min_gap_um
    lower = np.arange(k)[None, :] <= split[:, None]
    ps = np.where(np.isfinite(ps), ps, np.nan)
    h_hi = _weighted_median(ps, np.where(~lower, ws, 0.0))
    h_lo = _weighted_median(ps, np.where(lower, ws, 0.0))
    return h_hi, h_lo, valid


def _weighted_median(sorted_values: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Row-wise weighted median of values already sorted along axis 1 (NaN where no weight)."""
    cw = np.cumsum(weight, axis=1)
    total = cw[:, -1]
    idx = np.argmax(cw >= 0.5 * total[:, None], axis=1)
    out = np.take_along_axis(sorted_values, idx[:, None], axis=1)[:, 0]
    return np.where(total > 0, out, np.nan)


def own_amplitude(
    response: np.ndarray, period_um: np.ndarray, tan_theta: float, height_um: np.ndarray
) -> np.ndarray:
    """Amplitude a of a pure pixel, the least-squares fit of Z(P) = a·exp(−2πi·h·tanθ/P).

    response (L, N) complex; height_um (N,). Returns (N,) float64 (real part of the
    projection, the same estimator as :func:`mixture_amplitudes` with one side).
    """
    z = np.asarray(response)
    ph = -2.0 * np.pi * tan_theta * np.outer(1.0 / np.asarray(period_um, float), height_um)
    return np.real(np.exp(-1j * ph) * z).mean(axis=0)


def mixture_amplitudes(
    response: np.ndarray,
    period_um: np.ndarray,
    tan_theta: float,
    h_hi_um: np.ndarray,
    h_lo_um: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares (a_hi, a_lo), real, of Z(P) = Σ_j a_j·exp(−2πi·h_j·tanθ/P) over P.

    response (L, N) complex; h_hi_um, h_lo_um (N,). The normal equations are 2×2 per pixel:
    [[L, c], [c, L]]·a = Re(E^H·Z), c = Σ_P cos(2π(h_hi − h_lo)·tanθ/P). Sides whose phases
    stay equal over every period (c → L) make the system singular: NaN there.
    """
    z = np.asarray(response)
    inv_p = 1.0 / np.asarray(period_um, float)
    levels = inv_p.size
    e_hi = np.exp(-2j * np.pi * tan_theta * np.outer(inv_p, h_hi_um))
    e_lo = np.exp(-2j * np.pi * tan_theta * np.outer(inv_p, h_lo_um))
    b_hi = np.real(np.conj(e_hi) * z).sum(axis=0)
    b_lo = np.real(np.conj(e_lo) * z).sum(axis=0)
    c = np.cos(2.0 * np.pi * tan_theta * np.outer(inv_p, np.asarray(h_hi_um) - h_lo_um)).sum(0)
    det = levels * levels - c * c
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = det > 1e-3 * levels * levels
        a_hi = np.where(ok, (levels * b_hi - c * b_lo) / det, np.nan)
        a_lo = np.where(ok, (levels * b_lo - c * b_hi) / det, np.nan)
    return a_hi, a_lo


def deblur_fractions(
    blurred: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    known: np.ndarray,
    *,
    blur_sigma_px: float,
    iterations: int = 20,
) -> np.ndarray:
    """Own-area fractions F at pixels (rows, cols) from blurred-footprint fractions g = K * F.

    K is the separable 3×3 kernel [σ²/2, 1 − σ², σ²/2] per axis, the one with the variance
    of a Gaussian PSF of σ px (its MTF agrees to order 1/P² with exp(−2π²σ²/P²), which is
    what `quality.camera_blur_sigma_px` measures). ``blurred`` (N,): g at the pixels;
    ``known`` (H, W): F of their other 8-neighbours (0 or 1 on pure pixels; NaN counts ½).
    Projected Jacobi: F ← ½·F + ½·clip((g − Σ_{q≠p} K_q·F_q)/K_0, 0, 1). The eigenvalues of
    K/K_0 lie in (0, 1/K_0], so the damped step contracts while 1/K_0 < 4: the side
    weight is capped at 0.2 (K_0 ≥ 0.36; σ ≤ 0.63 px is modelled exactly, a wider PSF is
    deblurred as one of 0.63 px). Returns (N,) float64 (clip(g, 0, 1) where σ = 0).
    """
    g = np.asarray(blurred, np.float64)
    f = np.clip(g, 0.0, 1.0)
    if blur_sigma_px <= 0 or g.size == 0:
        return f
    a = min(0.5 * blur_sigma_px**2, 0.2)
    k1 = np.array([a, 1.0 - 2.0 * a, a])
    shape = known.shape
    index = np.full(shape, -1, np.intp)
    index[rows, cols] = np.arange(rows.size)
    fixed = np.zeros(rows.size)
    src, dst, wts = [], [], []
    for dr, dc in _OFFSETS8:
        w = k1[dr + 1] * k1[dc + 1]
        qr = np.clip(rows + dr, 0, shape[0] - 1)
        qc = np.clip(cols + dc, 0, shape[1] - 1)
        j = index[qr, qc]
        inside = j >= 0
        fixed += np.where(inside, 0.0, w * np.nan_to_num(known[qr, qc], nan=0.5))
        src.append(j[inside])
        dst.append(np.flatnonzero(inside))
        wts.append(np.full(int(inside.sum()), w))
    k0 = k1[1] * k1[1]
    src, dst, wts = np.concatenate(src), np.concatenate(dst), np.concatenate(wts)
    for _ in range(iterations):
        others = fixed + np.bincount(dst, weights=wts * f[src], minlength=rows.size)
        f = 0.5 * (f + np.clip((g - others) / k0, 0.0, 1.0))
    return f


def refine_cliff_heights(
    height_um: np.ndarray,
    fringe_height_um: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    samples: list[CliffSamples],
    *,
    pixel_size_um: float,
    blur_sigma_px: float,
    min_jump_um: float | None = None,
    radius: int = 5,
    sample: str = "point",
) -> CliffRefinement:
    """Heights at cliffs replaced by the side the pixel's centre lies on, or the area mean.

    sample: "point" (SCAN_BUNDLE.md: a pixel's height is the surface's at its centre; a
    straight wall through the pixel leaves the centre on the side holding more than half of
    its area, so the height is h_hi where f ≥ ½, else h_lo) or "area" (the area mean
    f·h_hi + (1 − f)·h_lo, what the pixel integrates).

    height_um: the surface so far (fused); fringe_height_um: the combined fringe heights
    (NaN where none), which locate cliffs and give the sides' heights (the fusion may
    smear a cliff over its neighbours); normals: the photometric normals (extrapolate the
    sides' heights); samples: per azimuth, the fringe response at least at every pixel
    within ``radius`` + 1 of a cliff (else that azimuth is not used there).

    Pixels processed: those next to a jump of the fringe heights (filled by the fused
    heights where they are NaN) beyond ``min_jump_um`` (default 2.6 pixel sizes, what
    ground of 69° rises over one pixel, far beyond the slopes the normals allow), their
    8-neighbours, and fused pixels within 3 px that disagree with the fringe heights by
    more than ½·min_jump_um (the fusion pulled them across the cliff). Each gets the
    sides of :func:`side_heights` (its gap ≥ ½·min_jump_um), the shares of each azimuth
    (:func:`mixture_amplitudes` over :func:`own_amplitude` of the same side's pure pixels;
    shares combined over azimuths and sides weighted by the squared side amplitude, the
    inverse variance of a share), :func:`deblur_fractions`, then f·h_hi + (1 − f)·h_lo.
    Pixels without two sides or without a lit side in any azimuth keep their height.

    Returns :class:`CliffRefinement`.
    """
    return refine_cliffs(
        height_um,
        fringe_height_um,
        normals,
        mask,
        samples,
        pixel_size_um=pixel_size_um,
        blur_sigma_px=blur_sigma_px,
        min_jump_um=min_jump_um,
        radius=radius,
        sample=sample,
    )[0]


def refine_cliffs(
    height_um: np.ndarray,
    fringe_height_um: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    samples: list[CliffSamples],
    *,
    pixel_size_um: float,
    blur_sigma_px: float,
    min_jump_um: float | None = None,
    radius: int = 5,
    sample: str = "point",
) -> tuple[CliffRefinement, np.ndarray]:
    """:func:`refine_cliff_heights`, and where the data showed a pixel near a cliff to be
    pure: (H, W) bool, the processed pixels (two sides found) that at least one azimuth saw,
    whose response a pure pixel at their own fringe height fits at least as well as the
    two sides' mixture, and whose own amplitude is at least 0.8 of their side's in every
    azimuth that saw them (a smaller one: part of the pixel is dark, the other side in
    shadow, and the response is the lit part's). Their fringe height is then a measurement
    of their side."""
    if sample not in ("point", "area"):
        raise ValueError(f"sample must be 'point' or 'area', got {sample!r}")
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool)
    s = float(pixel_size_um)
    jump = float(min_jump_um) if min_jump_um is not None else 2.6 * s
    fr = np.asarray(fringe_height_um, np.float32)
    base = np.where(np.isfinite(fr), fr, h)
    jumps = cliff_band(base, m, min_jump_um=jump, pixel_size_um=s, normals=normals)
    out = h.copy()
    pure_map = np.zeros(h.shape, bool)
    frac = np.full(h.shape, np.nan, np.float32)
    upper = np.full(h.shape, np.nan, np.float32)
    lower = np.full(h.shape, np.nan, np.float32)
    if not jumps.any() or not samples:
        return CliffRefinement(out, frac, upper, lower), pure_map
    band = _dilate(jumps, 1) & m
    near = _dilate(band, 3) & m
    with np.errstate(invalid="ignore"):
        pulled = near & np.isfinite(fr) & (np.abs(h - fr) > 0.5 * jump)
    process = band | pulled
    pure = m & ~band & ~pulled
    rows, cols = np.nonzero(process)
    h_hi, h_lo, valid = side_heights(
        base, normals, pure, rows, cols, pixel_size_um=s, min_gap_um=0.5 * jump, radius=radius
    )
    rows, cols, h_hi, h_lo = rows[valid], cols[valid], h_hi[valid], h_lo[valid]
    if rows.size == 0:
        return CliffRefinement(out, frac, upper, lower), pure_map
    mid = 0.5 * (h_hi + h_lo)
    shares, weights = [], []
    # Misfit of the two-side model and of a pure pixel at its own fringe height.
    misfit_two = np.zeros(rows.size)
    misfit_pure = np.zeros(rows.size)
    seen = np.zeros(rows.size, bool)
    whole = np.ones(rows.size, bool)  # every azimuth sees the whole pixel as its side
    own_h = fr[rows, cols].astype(np.float64)
    width = h.shape[1]
    flat = rows * width + cols
    for smp in samples:
        if smp.period_um.size < 2:  # one period cannot tell two sides apart
            continue
        a_hi, a_lo = _side_amplitudes(smp, base, pure, rows, cols, mid, radius)
        pos = np.searchsorted(smp.flat_index, flat)
        pos = np.clip(pos, 0, max(smp.flat_index.size - 1, 0))
        have = smp.flat_index.size > 0
        have = have & (smp.flat_index[pos] == flat) if have else np.zeros(flat.size, bool)
        z = smp.response(pos)
        m_hi, m_lo = mixture_amplitudes(z, smp.period_um, smp.tan_theta, h_hi, h_lo)
        used = have & np.isfinite(m_hi) & np.isfinite(z).all(axis=0)
        phase = -2j * np.pi * smp.tan_theta / smp.period_um[:, None]
        fit = m_hi * np.exp(phase * h_hi) + m_lo * np.exp(phase * h_lo)
        e_own = np.exp(phase * np.nan_to_num(own_h))
        a_own = own_amplitude(z, smp.period_um, smp.tan_theta, np.nan_to_num(own_h))
        pure_fit = a_own * e_own
        seen |= used
        # A pure pixel's own amplitude is its side's: a smaller one says part of the pixel
        # is dark in this azimuth (the other side in the projector's shadow), and the
        # response is that of the lit part, not of the pixel's centre.
        a_near = np.where(np.abs(own_h - h_hi) <= np.abs(own_h - h_lo), a_hi, a_lo)
        with np.errstate(invalid="ignore"):
            whole &= ~(used & (a_own < 0.8 * a_near))
        misfit_two += np.where(used, np.sum(np.abs(z - fit) ** 2, axis=0), 0.0)
        misfit_pure += np.where(used, np.sum(np.abs(z - pure_fit) ** 2, axis=0), 0.0)
        top = np.fmax(a_hi, a_lo)
        for a_side, share in ((a_hi, m_hi), (a_lo, None)):
            lit = have & np.isfinite(a_side) & (a_side > 0.1 * top) & np.isfinite(m_hi)
            with np.errstate(invalid="ignore", divide="ignore"):
                t = m_hi / a_side if share is not None else 1.0 - m_lo / a_side
            shares.append(np.where(lit, t, np.inf))
            weights.append(np.where(lit, np.square(np.nan_to_num(a_side)), 0.0))
    # Weighted median over the azimuths and sides: a shadow edge crossing the window makes
    # one side's brightness at the pixel differ from its neighbours' (that share is then
    # wrong, not noisy); the median follows the consistent majority.
    if not shares:
        return CliffRefinement(out, frac, upper, lower), pure_map
    t_all, w_all = np.stack(shares, axis=1), np.stack(weights, axis=1)
    order = np.argsort(t_all, axis=1)
    t_all = np.take_along_axis(t_all, order, axis=1)
    g = _weighted_median(
        np.where(np.isfinite(t_all), t_all, np.nan), np.take_along_axis(w_all, order, axis=1)
    )
    # Refined only where the data prefer two sides to a pure pixel at its own fringe height
    # (none: the fringes gave up on it). Sides read from ground that is not two planes
    # (several surfaces in the window, at coarse pixels) fail this test.
    is_pure = np.isfinite(own_h) & (misfit_pure <= misfit_two)
    trusted = is_pure & seen & whole
    pure_map[rows[trusted], cols[trusted]] = True
    ok = np.isfinite(g) & ~is_pure
    # A pure pixel the fusion pulled across the cliff gets its own fringe height back.
    back = is_pure & pulled[rows, cols]
    out[rows[back], cols[back]] = own_h[back].astype(np.float32)
    r_ok, c_ok = rows[ok], cols[ok]
    known = _pure_sides(base, r_ok, c_ok, mid[ok], h.shape)
    f = deblur_fractions(g[ok], r_ok, c_ok, known, blur_sigma_px=blur_sigma_px)
    if sample == "point":
        out[r_ok, c_ok] = np.where(f >= 0.5, h_hi[ok], h_lo[ok]).astype(np.float32)
    else:
        out[r_ok, c_ok] = (f * h_hi[ok] + (1.0 - f) * h_lo[ok]).astype(np.float32)
    frac[r_ok, c_ok] = f
    upper[r_ok, c_ok] = h_hi[ok]
    lower[r_ok, c_ok] = h_lo[ok]
    return CliffRefinement(out, frac, upper, lower), pure_map


class UnmeasuredJumps(NamedTuple):
    """Output of :func:`unmeasured_jumps`, (H, W) bool each."""

    cliff: np.ndarray  # ground at two levels around the pixel: its side is unknown
    steep: np.ndarray  # steep ground whose normals explain the jump


def unmeasured_jumps(
    height_um: np.ndarray,
    fringe_height_um: np.ndarray,
    normals: np.ndarray | None,
    mask: np.ndarray,
    decided: np.ndarray,
    *,
    valid: np.ndarray,
    pixel_size_um: float,
    min_jump_um: float | None = None,
) -> UnmeasuredJumps:
    """Pixels next to a jump of the heights that no measurement placed.

    The zone: pixels within one pixel of a jump of the heights (the fringe heights,
    ``height_um`` where they have none) beyond ``min_jump_um`` (default 2.6 pixel sizes,
    what ground of 69° rises over one pixel) more than the normals predict (`cliff_band`),
    without a valid fringe height (``valid``: near a jump no single fringe height is one)
    and not ``decided`` (the caller's evidence: the fringe response over the periods placed
    the pixel, `refine_cliffs`). Split by the normals, trusted up to 85° here:

    cliff: the normals do not explain the jump either: a vertical wall shows no area, so
        the pixels beside it keep their sides' normals. SCAN_BUNDLE.md: a pixel's height is
        the surface's at its centre, so a pixel at a cliff has the height of the side its
        centre is on, never one between and never the other side's; here nothing told
        which side that is (a wrong guess is a spike of the cliff's height);
    steep: they do: steep ground (a break face, a tablet's side) that is seen, every
        height along it a point sample of it.
    """
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool) & np.isfinite(h)
    fr = np.asarray(fringe_height_um, np.float32)
    s = float(pixel_size_um)
    jump = float(min_jump_um) if min_jump_um is not None else 2.6 * s
    base = np.where(np.isfinite(fr), fr, h)
    jumps = cliff_band(base, m, min_jump_um=jump, pixel_size_um=s, normals=normals)
    none = np.zeros(h.shape, bool)
    if not jumps.any():
        return UnmeasuredJumps(none, none.copy())
    near = _dilate(jumps, 1)
    zone = near & m & ~np.asarray(valid, bool) & ~np.asarray(decided, bool)
    if normals is None or not zone.any():
        return UnmeasuredJumps(zone, none)
    wall = cliff_band(
        base, m, min_jump_um=jump, pixel_size_um=s, normals=normals, max_slope_deg=85.0
    )
    cliff = zone & _dilate(wall, 1)
    return UnmeasuredJumps(cliff, zone & ~cliff)


class RegionCheck(NamedTuple):
    """Output of :func:`check_refinement`: the heights kept, and what acted where."""

    height_um: np.ndarray  # (H, W) float32
    acted: np.ndarray  # (H, W) bool, pixels whose refined height was kept
    regions: int  # connected regions of changed pixels
    stood_down: int  # regions given their input heights back
    stood_down_pixels: int


def check_refinement(
    before_um: np.ndarray,
    after_um: np.ndarray,
    fringe_height_um: np.ndarray,
    mask: np.ndarray,
    *,
    radius: int = 5,
) -> RegionCheck:
    """Keep a cliff refinement region by region only where the measurements support it.

    A refinement moves a pixel onto one side of a wall; both sides' heights are measured by
    the fringes around it. So each changed pixel must lie within the range [min, max] of
    the fringe heights of the unchanged mask pixels in its (2·radius + 1)² window. A pixel
    outside it (a side extrapolated through a grazing normal, a chip floor read as a
    terrace) contradicts the two-sides model there; the region it spoils — it and the
    changed pixels among its 8-neighbours, which share its side estimates (their windows
    overlap by all but one row) — stands down and gets its input heights back. A whole
    cliff band is not one region: on a long wall most pixels are right where a few fail.

    before_um, after_um, fringe_height_um: (H, W) µm (fringe NaN where none); mask bool.
    """
    b = np.asarray(before_um, np.float32)
    a = np.asarray(after_um, np.float32)
    m = np.asarray(mask, bool)
    with np.errstate(invalid="ignore"):
        changed = m & np.isfinite(a) & ~(a == b)
    eight = np.ones((3, 3), bool)
    if not changed.any():
        return RegionCheck(a.copy(), changed, 0, 0, 0)
    fr = np.asarray(fringe_height_um, np.float32)
    known = m & ~changed & np.isfinite(fr)
    size = 2 * radius + 1
    hi = ndimage.maximum_filter(
        np.where(known, fr, -np.inf), size=size, mode="constant", cval=-np.inf
    )
    lo = ndimage.minimum_filter(
        np.where(known, fr, np.inf), size=size, mode="constant", cval=np.inf
    )
    with np.errstate(invalid="ignore"):
        bad = changed & ~((a >= lo) & (a <= hi))
    revert = ndimage.binary_dilation(bad, structure=eight) & changed
    _, n = ndimage.label(changed, structure=eight)
    _, n_bad = ndimage.label(revert, structure=eight)
    out = np.where(revert, b, a).astype(np.float32)
    return RegionCheck(out, changed & ~revert, int(n), int(n_bad), int(revert.sum()))


def _dilate(a, r):
    """Binary dilation by the (2r + 1)² square."""
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate(a.astype(np.uint8), k).astype(bool)


def _side_amplitudes(smp, base, pure, rows, cols, mid, radius):
    """Median own amplitude of the pure pixels above and below ``mid`` in the window."""
    nan = np.full(rows.size, np.nan)
    if smp.flat_index.size == 0:
        return nan, nan
    rr, cc = base.shape
    offs = [(dr, dc) for dr in range(-radius, radius + 1) for dc in range(-radius, radius + 1)]
    qr = np.clip(rows[:, None] + np.array([o[0] for o in offs]), 0, rr - 1)
    qc = np.clip(cols[:, None] + np.array([o[1] for o in offs]), 0, cc - 1)
    q = qr * cc + qc
    take = pure.ravel()[q] & np.isfinite(base.ravel()[q])
    need = np.unique(q[take])
    pos = np.clip(np.searchsorted(smp.flat_index, need), 0, smp.flat_index.size - 1)
    found = smp.flat_index[pos] == need
    amp_need = np.full(need.size, np.nan)
    hn = base.ravel()[need[found]]
    amp_need[found] = own_amplitude(
        smp.response(pos[found]), smp.period_um, smp.tan_theta, hn.astype(np.float64)
    )
    a = np.full(q.shape, np.nan)
    a[take] = amp_need[np.searchsorted(need, q[take])]
    above = base.ravel()[q] > mid[:, None]
    d2 = np.array([o[0] * o[0] + o[1] * o[1] for o in offs], float)
    w = np.where(np.isfinite(a), 1.0 / np.maximum(d2, 1.0), 0.0)
    out = []
    for side in (above, ~above):
        v = np.where(side & np.isfinite(a), a, np.inf)
        order = np.argsort(v, axis=1)
        vs = np.take_along_axis(v, order, axis=1)
        ws = np.take_along_axis(np.where(side, w, 0.0), order, axis=1)
        out.append(_weighted_median(np.where(np.isfinite(vs), vs, np.nan), ws))
    return out[0], out[1]


def _pure_sides(base, rows, cols, mid, shape):
    """F = 1 / 0 at the 8-neighbours of the refined pixels that lie above / below their mid
    height (the pure pixels around a cliff), NaN elsewhere."""
    known = np.full(shape, np.nan)
    rr, cc = shape
    for dr, dc in _OFFSETS8:
        qr = np.clip(rows + dr, 0, rr - 1)
        qc = np.clip(cols + dc, 0, cc - 1)
        known[qr, qc] = (base[qr, qc] > mid).astype(float)
    return known
