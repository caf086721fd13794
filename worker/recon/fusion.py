"""Default fusion of photometric normals and fringe heights: one weighted least-squares problem.

In the spirit of Nehab, Rusinkiewicz, Davis & Ramamoorthi 2005 ("Efficiently combining
positions and normals for precise 3D geometry"), but on the camera's pixel grid: the fused
height h minimises

    Σ_edges w_e (Δh_e − s·ḡ_e)²  +  Σ_pixels λ_p (h_p − f_p)²,

with ḡ_e the mean slope of the edge's two pixels (from the normals), s the pixel size and f
the fringe heights. The weights are inverse variances, so the solution is the maximum-
likelihood surface under Gaussian noise:

- slope term: isotropic angular noise σ_θ gives the slopes the covariance
  σ_θ²(1 + |g|²)(I + g gᵀ) — σ_θ/n_z² along the tilt (d tan α = dα/cos²α), σ_θ/n_z across
  it — so an x-edge's step has the error s·σ_θ·√((1 + |g|²)(1 + g_x²)) µm (a y-edge's with
  g_y); steep walls are down-weighted by up to n_z⁴, and pixels without a normal carry no
  slope term;
- height term: λ = 1/σ_f², σ_f the fringe height noise; pixels without a fringe height
  (shadowed for every azimuth) have λ = 0 and are reached by the slopes alone.

Robustness (real data has unwrapping errors, specular spikes and cliffs the normals cannot
express): before solving, edges whose slope step contradicts the fringes' own step far
beyond both noises are down-weighted (`_cut_discontinuities`); after a first solve both
terms are re-weighted by Cauchy weights 1/(1 + (r/(k·σ))²), k = `outlier_sigmas` — fringe
heights off the surface, and edges whose solved step disagrees with their target (only
where the normals show a break, `_bent_edges`: on smooth ground an island of bad fringe
heights must not cut itself loose) — and the problem is solved again, warm-started.

The weights' scale comes from predicted noise (photometric residual, fringe phase noise),
which can be wrong by a large factor (a light calibration bias leaves a small residual): after
the first solve one round of variance component estimation (`variance_factors`, Förstner
1979) rescales each class of slope and height terms by what its residuals say.

Edge targets use the four-point cell average of the slopes where it stands out of the noise
(`cell_average_targets_um`); the final solve's slopes are also low-passed across their edges
by a maximally flat half-band filter (`transverse_mean_slopes`). A low-frequency bias of the
normals is removed before (`normal_bias`). `sharpen_heights` undoes a measured camera blur
afterwards.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numpy as np
from scipy import ndimage

from worker.recon.arrays import fast_median
from worker.recon.integrate import (
    _bbox,
    _label_stats,
    edge_targets_um,
    slopes_from_normals,
    solve_screened_poisson,
)
from worker.recon.parallel import run_blocks

__all__ = [
    "cell_average_targets_um",
    "PIXEL_AREA_VAR_PX2",
    "fuse_default",
    "point_sample_sigma_px",
    "sharpen_heights",
    "term_leverages",
    "transverse_mean_slopes",
    "variance_factors",
]


def fuse_default(
    normals: np.ndarray,
    fringe_height_um: np.ndarray,
    *,
    pixel_size_um: float,
    mask: np.ndarray,
    normal_sigma_rad: np.ndarray | float,
    height_sigma_um: np.ndarray | float,
    outlier_sigmas: float = 4.0,
    robust_passes: int = 1,
    variance_components: bool = True,
    variance_classes: int = 8,
    rtol: float = 2e-5,
    workers: int = 1,
) -> np.ndarray:
    """Fuse normals and fringe heights into one height map.

    normals: (H, W, 3) unit normals, n_z < 0, NaN where none.
    fringe_height_um: (H, W) heights from the fringes in µm, NaN where none.
    pixel_size_um: s > 0. mask: (H, W) bool, pixels to reconstruct.
    normal_sigma_rad: angular noise of each normal, (H, W) or scalar > 0 (inf: unusable).
    height_sigma_um: noise of each fringe height, (H, W) or scalar > 0 (inf: unusable).
    workers: threads of the solver's DCTs (the result does not depend on it).
    Returns (H, W) float32 heights in µm, NaN off the mask. Where a connected part of the mask
    has no fringe height at all its mean is set to 0.
    """
    n = np.asarray(normals)
    f = np.asarray(fringe_height_um, dtype=np.float32)
    m = np.asarray(mask, bool)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3), got {n.shape}")
    if f.shape != n.shape[:2]:
        raise ValueError(f"fringe_height_um shape {f.shape} does not match normals {n.shape}")
    if m.shape != f.shape:
        raise ValueError(f"mask shape {m.shape} does not match normals {n.shape}")
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    sig_n = np.broadcast_to(np.asarray(normal_sigma_rad, np.float32), f.shape)
    sig_f = np.broadcast_to(np.asarray(height_sigma_um, np.float32), f.shape)
    if np.any(sig_n <= 0) or np.any(sig_f <= 0):
        raise ValueError("normal_sigma_rad and height_sigma_um must be > 0")
    out = np.full(f.shape, np.nan, np.float32)
    if not m.any():
        return out
    r0, r1, c0, c1 = _bbox(m)
    crop = (slice(r0, r1), slice(c0, c1))
    m_c = m[crop]
    s = float(pixel_size_um)

    gx, gy = slopes_from_normals(n[crop], min_abs_nz=0.05)
    nz = np.abs(n[crop][..., 2].astype(np.float32))
    has_slope = m_c & np.isfinite(gx) & np.isfinite(gy) & np.isfinite(sig_n[crop])
    # Isotropic angular noise σ on a normal of slope g gives the slopes the covariance
    # σ²(1 + |g|²)(I + g gᵀ): (1 + |g|²)² = 1/n_z⁴ along the tilt, 1/n_z² across it.
    with np.errstate(divide="ignore", invalid="ignore"):
        gx2, gy2 = np.square(np.nan_to_num(gx)), np.square(np.nan_to_num(gy))
        sig_x = s * sig_n[crop] * np.sqrt((1 + gx2 + gy2) * (1 + gx2))
        sig_y = s * sig_n[crop] * np.sqrt((1 + gx2 + gy2) * (1 + gy2))
        step_sigma = s * sig_n[crop] / np.square(nz)  # along the tilt: the break test's scale
        w_px = np.where(has_slope, 1.0 / np.square(sig_x), 0).astype(np.float32, copy=False)
        w_py = np.where(has_slope, 1.0 / np.square(sig_y), 0).astype(np.float32, copy=False)
    # An edge's target is the mean of two slopes; with independent errors its inverse variance
    # is twice the harmonic mean of the pixel weights, but neighbouring normals share errors
    # (smooth shading, interreflections), so the conservative harmonic mean is used. It is 0
    # when either end has no slope.
    wx = _edge_weight(w_px[:, 1:], w_px[:, :-1])
    wy = _edge_weight(w_py[1:, :], w_py[:-1, :])
    tx, ty = cell_average_targets_um(gx, gy, pixel_size_um=s)
    # Mask pixels without a normal are bridged by a faint membrane (flat target) so that the
    # ones without a fringe height either follow their neighbours instead of floating free.
    in_x, in_y = m_c[:, 1:] & m_c[:, :-1], m_c[1:, :] & m_c[:-1, :]
    gap_x, gap_y = in_x & ~(wx > 0), in_y & ~(wy > 0)
    wx, tx = _bridge(wx, in_x, tx)
    wy, ty = _bridge(wy, in_y, ty)

    def final_targets():
        # The final solve's targets are also averaged across their edges where the slopes
        # allow it; the weights and the variance factors stay those of the single-pixel
        # targets (the averaged targets share pixels between neighbouring edges, which the
        # factors, estimated as if edges were independent, would take for extra precision).
        ax, ay = transverse_mean_slopes(
            np.where(has_slope, gx, np.nan), np.where(has_slope, gy, np.nan)
        )
        sx, sy = cell_average_targets_um(ax, ay, pixel_size_um=s)
        return np.where(gap_x, np.float32(0), sx), np.where(gap_y, np.float32(0), sy)

    # What only the later steps need (the final targets, the terms' leverages) is computed
    # beside the first solve, which leaves a core idle, when there are workers for it.
    side = ThreadPoolExecutor(max_workers=1) if workers > 1 else None

    def beside(job):
        """job's result, to fetch by calling: computed in the side thread if any, else then."""
        return job if side is None else side.submit(job).result

    targets = beside(final_targets)

    f_c = f[crop]
    has_f = m_c & np.isfinite(f_c) & np.isfinite(sig_f[crop])
    with np.errstate(divide="ignore"):
        lam = np.where(has_f, 1.0 / np.square(sig_f[crop]), 0).astype(np.float32, copy=False)

    cut_x = cut_y = None
    if has_f.any() and outlier_sigmas > 0:
        cut_x, cut_y = _bent_edges(gx, gy, step_sigma, s, k=outlier_sigmas)
        wx, wy, stranded = _cut_discontinuities(
            f_c,
            sig_f[crop],
            has_f,
            wx,
            wy,
            tx,
            ty,
            cut_x,
            cut_y,
            k=outlier_sigmas,
            max_step=np.float32(s * _MAX_SLOPE),
        )
        lam = np.where(stranded, np.float32(0), lam)
    parts = ndimage.label(m_c)  # the mask's connected parts: anchored, then zero-mean
    lam = _anchor_parts_without_data(parts, m_c, lam, wx, wy)
    x0 = np.where(has_f, f_c, np.float32(fast_median(f_c[has_f]) if has_f.any() else 0))
    robust_pass = has_f.any() and outlier_sigmas > 0 and robust_passes > 0
    # With a robust pass to follow, the first solve only sets the weights (and warm-starts
    # the last solve): 1e-3 is enough for residuals judged at 4σ.
    first_rtol = max(rtol, 1e-3) if robust_pass else rtol
    estimate = variance_components and has_f.any()
    leverages = beside(partial(term_leverages, lam, wx, wy)) if estimate else None
    if side is not None:
        side.shutdown(wait=False)  # the jobs run on; nothing else is submitted
    sol = solve_screened_poisson(
        tx, ty, wx, wy, data_um=f_c, data_weight=lam, x0_um=x0, rtol=first_rtol, workers=workers
    )
    h = sol.height_um
    sx, sy = targets()
    if estimate:
        # One round of variance component estimation on the pilot solve: dividing each
        # class's weights by its factor balances the groups as the data say, and the
        # robust thresholds below become those of the estimated noise.
        fx, fy, ff = variance_factors(
            h,
            f_c,
            lam,
            wx,
            wy,
            tx,
            ty,
            cut_x=cut_x,
            cut_y=cut_y,
            classes=variance_classes,
            leverages=leverages(),
            workers=workers,
        )
        wx, wy, lam = wx / fx, wy / fy, lam / ff
        sig_f_c = sig_f[crop] * np.sqrt(ff)
        if not robust_pass:
            h = solve_screened_poisson(
                sx, sy, wx, wy, data_um=f_c, data_weight=lam, x0_um=h, rtol=rtol, workers=workers
            ).height_um
    else:
        sig_f_c = sig_f[crop]
    if robust_pass:
        for _ in range(robust_passes):
            rwx, rwy, rlam = _cauchy_weights(
                h,
                f_c,
                sig_f_c,
                has_f,
                lam,
                wx,
                wy,
                tx,
                ty,
                cut_x,
                cut_y,
                k=np.float32(outlier_sigmas),
                workers=workers,
            )
            sol = solve_screened_poisson(
                sx, sy, rwx, rwy, data_um=f_c, data_weight=rlam, x0_um=h, rtol=rtol, workers=workers
            )
            h = sol.height_um
    h = _zero_mean_where_no_data(parts, h, m_c, has_f)
    out[crop] = np.where(m_c, h, np.nan)
    return out


def variance_factors(
    h, f, lam, wx, wy, tx, ty, *, cut_x=None, cut_y=None, classes=8, leverages=None, workers=1
):
    """Variance factors of the slope and height terms, per class of predicted noise.

    Variance component estimation (Helmert 1924; Förstner 1979; Koch 1999 §3.6): if the
    weights w = 1/σ² of a group of observations are right up to one factor, a residual r
    of weight w has E[w·r²] = σ̂²·(1 − ℓ), ℓ its leverage (diagonal of the hat matrix),
    so σ̂² = Σ w r² / Σ(1 − ℓ) (the group's redundancy). Here σ̂² is the square of the
    normalised MAD of u = r·√(w/(1 − ℓ)), so that cliffs and unwrapping errors (the robust
    pass's business) do not inflate it. Each group is split into `classes` quantile classes
    of its weights, each with its own factor: where the predicted noise (photometric
    residual, azimuths used, crease term) ranks the observations wrongly, the classes even
    it out. The leverage of a height term is that of a pixel of a homogeneous lattice with
    the pixel's edge stiffness w_p (a quarter of its edges' summed weights) and data weight
    λ_p: ℓ_p = m·G(m), m = λ_p/w_p, G the diagonal of (m + L)⁻¹ for the 5-point Laplacian
    on the infinite grid (`_lattice_green_diag`); the slope terms share the rest of the
    trace, n_pixels − Σℓ_p, evenly. Edges that may be cut (`cut_x`, `cut_y`) are left out
    of the estimate (they take their class's factor).

    h: solved (H, W) µm; f, lam: fringe heights and their weights; wx, wy, tx, ty: slope
    terms as in `fuse_default`; leverages: `term_leverages(lam, wx, wy)` if computed
    already (they do not depend on h). Returns (fx, fy, ff): factors shaped like wx, wy, lam
    (1 where a class has fewer than 25 residuals); dividing the weights by them makes them
    honest. workers > 1: the slope and the height factors are estimated in two threads.
    """
    has = lam > 0
    lev_p, lev_e = term_leverages(lam, wx, wy) if leverages is None else leverages

    def edge_factors():
        with np.errstate(divide="ignore", invalid="ignore"):
            ux = (h[:, 1:] - h[:, :-1] - tx) * np.sqrt(wx / (1 - lev_e))
            uy = (h[1:, :] - h[:-1, :] - ty) * np.sqrt(wy / (1 - lev_e))
        keep_x = wx > 0 if cut_x is None else (wx > 0) & ~cut_x
        keep_y = wy > 0 if cut_y is None else (wy > 0) & ~cut_y
        factor = _class_factors(*_residual_sample((wx, ux, keep_x), (wy, uy, keep_y)), classes)
        return factor(wx), factor(wy)

    def height_factors():
        with np.errstate(divide="ignore", invalid="ignore"):
            uf = (h - f) * np.sqrt(lam / np.maximum(1 - lev_p, 1e-2))
        factor = _class_factors(*_residual_sample((lam, uf, has)), classes)
        return np.where(has, factor(lam), np.float32(1))

    (fx, fy), ff = _side_by_side(edge_factors, height_factors, workers=workers)
    return fx, fy, ff


def _side_by_side(first, second, *, workers):
    """(first(), second()): the two unlike jobs in two threads when workers > 1."""
    if workers < 2:
        return first(), second()
    with ThreadPoolExecutor(max_workers=1) as pool:
        job = pool.submit(first)
        return job.result(), second()


def term_leverages(lam, wx, wy):
    """Leverages of the terms (`variance_factors`): (H, W) float32 of the height terms
    (0 without one, 1 for a pixel without edges) and the one shared by every slope term."""
    has = lam > 0
    stiff = np.zeros_like(lam)
    stiff[:, 1:] += wx
    stiff[:, :-1] += wx
    stiff[1:, :] += wy
    stiff[:-1, :] += wy
    with np.errstate(divide="ignore", invalid="ignore"):
        m = lam / (stiff / 4)
    lev_p = np.where(has, np.where(stiff > 0, _hat_diag(m), 1), 0).astype(np.float32, copy=False)
    n_edges = int(np.count_nonzero(wx) + np.count_nonzero(wy))
    n_active = int(np.count_nonzero(has | (stiff > 0)))
    lev_e = float(np.clip((n_active - lev_p.sum()) / max(n_edges, 1), 0, 0.99))
    return lev_p, lev_e


def _residual_sample(*groups, size=100_000):
    """(weights, residuals) of every step-th term with a finite residual, step such that
    about `size` remain (100k residuals fix a class's MAD to ~1 %).

    groups: (weights, residuals, keep) arrays, the terms taken where keep, group after
    group in C order: the values of concatenating w[keep & finite u] over the groups, then
    [::step], picked by index instead of copying every kept term.
    """
    picks = [np.flatnonzero(keep & np.isfinite(u)) for _, u, keep in groups]
    step = max(1, sum(p.size for p in picks) // size)
    weights, residuals = [], []
    before = 0  # terms of the earlier groups: the sample's phase in this one
    for (w, u, _), p in zip(groups, picks, strict=True):
        chosen = p[-before % step :: step]
        weights.append(np.ravel(w).take(chosen))
        residuals.append(np.ravel(u).take(chosen))
        before += p.size
    return np.concatenate(weights), np.concatenate(residuals)


def _class_factors(weights, u, classes, max_factor=1e4):
    """A function weight → (normalised MAD of u)² of that weight's quantile class;
    weights, u: a sample of finite residuals (`_residual_sample`)."""
    classes = max(1, min(classes, u.size // 25))
    if u.size < 25:
        return lambda w: np.ones(np.shape(w), np.float32)
    bounds = np.quantile(weights, np.linspace(0, 1, classes + 1)[1:-1])
    cls = np.searchsorted(bounds, weights)
    # Classes that tied weights leave (nearly) empty take the pooled value.
    pooled = float(np.median(np.abs(u)))
    counts = np.bincount(cls, minlength=classes)
    mad = np.array(
        [np.median(np.abs(u[cls == i])) if counts[i] >= 25 else pooled for i in range(classes)]
    )
    fac = np.clip(np.square(1.4826 * mad), 1 / max_factor, max_factor).astype(np.float32)
    return lambda w: np.take(fac, _class_index(bounds, w))


def _class_index(bounds, w):
    """np.searchsorted(bounds, w) for a few sorted bounds: one comparison per bound on a
    uint8 count is several times faster than a binary search per element (NaN: the end)."""
    w = np.asarray(w)
    idx = np.zeros(w.shape, np.uint8 if len(bounds) < 255 else np.intp)
    for b in bounds:
        idx += ~(w <= b)
    return idx


def _lattice_green_diag(m):
    """G(m) = (1/4π²)∬ dk/(m + 4sin²(k_x/2) + 4sin²(k_y/2)) over [−π, π]², m > 0.

    The k_y integral is exact, (1/2π)∫dk/(a + 4sin²(k/2)) = 1/√(a(a+4)); the k_x one is a
    midpoint rule on a table of m, interpolated in log m (G ~ ln(32/m)/4π for small m,
    ~1/m for large m).
    """
    m = np.asarray(m, np.float64)
    table_m, table_g = _GREEN_TABLE
    lm = np.log(np.clip(m, table_m[0], table_m[-1]))
    return np.exp(np.interp(lm, np.log(table_m), np.log(table_g)))


def _green_table():
    ms = np.logspace(-9, 6, 121)
    k = (np.arange(8192) + 0.5) * (np.pi / 8192)
    a = ms[:, None] + 4 * np.square(np.sin(k / 2))[None, :]
    g = np.mean(1 / np.sqrt(a * (a + 4)), axis=1)
    return ms, g


_GREEN_TABLE = _green_table()


def _hat_diag(m):
    """Leverage m·G(m) of a height term on the homogeneous lattice (in [0, 1])."""
    return np.clip(m * _lattice_green_diag(m), 0, 1)


def cell_average_targets_um(
    gx: np.ndarray, gy: np.ndarray, *, pixel_size_um: float, significance: float = 3.0
):
    """Edge targets h[c+1] − h[c] from per-pixel slopes, exact for cubics where it matters.

    A pixel's normal gives the slope of the pixel-averaged surface H at its centre (∂H/∂x
    is the pixel mean of ∂h/∂x), so an edge's step is the integral of that slope over one
    pixel. The trapezoid rule s·(g₀ + g₁)/2 (`integrate.edge_targets_um`) errs by
    (s³/12)·g'' there, i.e. it blurs the surface by an extra variance s²/6 along the edge,
    which rounds wedge bottoms and rims; the four-point cell average
    s·(−g₋₁ + 13g₀ + 13g₁ − g₂)/24 is exact for cubic H. Its correction term
    −s·(g₋₁ − g₀ − g₁ + g₂)/24 is a second difference of the slopes, mostly noise on smooth
    ground: it is kept where it stands out of that noise, through the non-negative garrote
    max(0, 1 − (k·σ_c/c)²) (Breiman 1995; σ_c = 1.4826·MAD of c, k = `significance`), so
    that flat ground keeps the trapezoid's lower noise. Where a neighbour's slope is missing
    the trapezoid value stays.

    gx, gy: (H, W) slopes, NaN where none. Returns tx (H, W−1), ty (H−1, W) in µm.
    """
    s = float(pixel_size_um)
    tx, ty = edge_targets_um(gx, gy, pixel_size_um=s)
    k = np.float32(s / 24)
    cx = (gx[:, :-3] - gx[:, 1:-2] - gx[:, 2:-1] + gx[:, 3:]) * k
    cy = (gy[:-3] - gy[1:-2] - gy[2:-1] + gy[3:]) * k
    tx = tx.copy()
    ty = ty.copy()
    tx[:, 1:-1] -= _garrote(cx, significance)
    ty[1:-1] -= _garrote(cy, significance)
    return tx, ty


def transverse_mean_slopes(gx: np.ndarray, gy: np.ndarray, *, significance: float = 3.0):
    """Slopes for the edge targets, low-passed across the edge above half the Nyquist frequency.

    An x-edge's step integrates ∂h/∂x over the width of its pixels; the pixels above and
    below measure the same slope with their own noise. Across the edge the slopes are
    filtered by the maximally flat half-band filter [−1 4 10 4 −1]/16, whose response
    (10 + 8cos k − 2cos 2k)/16 is 1 to fourth order at k = 0 (exact for a cubic across the
    edge — no ∇² blur, unlike a [1 2 1]/4 mean), 3/4 at half the Nyquist frequency and 0 at
    it. Near the Nyquist frequency the camera (pixel box and PSF) has left little of the
    surface, while the normals' white noise is flat up to it: the filter removes the upper
    half of that band, about half of the noise variance (Σk² = 0.52), and keeps the
    wedges. The Fried (1977) cell model averages over the cell's two rows for the same
    reason, with a [1 1]/2 that also blurs. A deviation g − ḡ that stands out of the noise (a
    feature narrower than the filter, along the edge) keeps its non-negative garrote share
    max(0, 1 − (k·σ_d/d)²) (Breiman 1995; σ_d = 1.4826·MAD of d, k = `significance`). A
    missing neighbour counts as the pixel itself.

    gx, gy: (H, W) slopes, NaN where none. Returns (gx filtered along columns, gy filtered
    along rows), float32, NaN where the input is.
    """

    def across(g, axis):
        g = np.asarray(g, np.float32)
        smooth = g.copy()
        for shift, tap in _HALF_BAND:
            nb = _shifted(g, shift, axis)
            smooth += np.float32(tap) * np.where(np.isfinite(nb), nb - g, 0)
        dev = g - smooth
        kept = _garrote_factor(dev, significance) * np.nan_to_num(dev)
        return (smooth + kept).astype(np.float32, copy=False)

    with np.errstate(invalid="ignore"):
        return across(gx, 0), across(gy, 1)


# Off-centre taps of [−1 4 10 4 −1]/16 as (offset, weight).
_HALF_BAND = ((-2, -1 / 16), (-1, 4 / 16), (1, 4 / 16), (2, -1 / 16))


def _shifted(a, shift, axis):
    """a moved by `shift` along `axis` (out[i] = a[i + shift]), NaN where it runs out."""
    out = np.full_like(a, np.nan)
    n = a.shape[axis]
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    if shift >= 0:
        src[axis], dst[axis] = slice(shift, n), slice(0, n - shift)
    else:
        src[axis], dst[axis] = slice(0, n + shift), slice(-shift, n)
    out[tuple(dst)] = a[tuple(src)]
    return out


def _garrote_factor(c, significance):
    """max(0, 1 − (k·σ/c)²), σ the robust spread of c; 0 where c is NaN."""
    finite = c[np.isfinite(c)][::3]
    if finite.size < 25:
        return np.zeros_like(c)
    noise = 1.4826 * float(fast_median(np.abs(finite - fast_median(finite))))
    floor = np.float32(np.square(significance * noise))
    c2 = np.square(np.nan_to_num(c, nan=0.0, posinf=0.0, neginf=0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(c2 > floor, 1 - floor / c2, np.float32(0)).astype(np.float32, copy=False)


def _garrote(c, significance):
    """c shrunk by max(0, 1 − (k·σ/c)²), σ the robust spread of c; 0 where c is NaN."""
    finite = c[np.isfinite(c)][::3]  # a third of the values fixes the MAD to < 1 %
    if finite.size < 25:
        return np.zeros_like(c)
    noise = 1.4826 * float(fast_median(np.abs(finite - fast_median(finite))))
    floor = np.float32(np.square(significance * noise))
    c = np.nan_to_num(c, nan=0.0, posinf=0.0, neginf=0.0)
    c2 = np.square(c)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(c2 > floor, c * (1 - floor / c2), np.float32(0)).astype(
            np.float32, copy=False
        )


# Rows of `_cauchy_weights`' blocks hold about this many pixels (their dozen arrays stay in
# the core's cache).
_ROBUST_BLOCK_PX = 65_536


def _cauchy_weights(h, f, sig_f, has_f, lam, wx, wy, tx, ty, cut_x, cut_y, *, k, workers=1):
    """The robust pass's weights (wx·ρx, wy·ρy, λ·ρf), ρ = 1/(1 + (r/(k·σ))²) the Cauchy
    weight of each term's residual r under the solved h (`fuse_default`): fringe heights
    where has_f, edges only where cut_x / cut_y allow (ρ = 1 elsewhere, and where r/σ is
    NaN). Elementwise, in blocks of rows shared out between `workers` threads.
    """
    rows, cols = h.shape
    out_x, out_y, out_f = np.empty_like(wx), np.empty_like(wy), np.empty_like(lam)
    step = max(1, _ROBUST_BLOCK_PX // cols)

    def cauchy(z):
        return 1 / (1 + np.square(np.nan_to_num(z)))

    def block(r0):
        r1 = min(r0 + step, rows)
        hb = h[r0:r1]
        with np.errstate(invalid="ignore", divide="ignore"):
            zf = (hb - f[r0:r1]) / (k * sig_f[r0:r1])
            zx = (hb[:, 1:] - hb[:, :-1] - tx[r0:r1]) * np.sqrt(wx[r0:r1]) / k
        np.multiply(lam[r0:r1], np.where(has_f[r0:r1], cauchy(zf), 1), out=out_f[r0:r1])
        np.multiply(wx[r0:r1], np.where(cut_x[r0:r1], cauchy(zx), 1), out=out_x[r0:r1])
        e1 = min(r1, rows - 1)  # y-edge e joins rows e and e + 1
        if r0 < e1:
            with np.errstate(invalid="ignore", divide="ignore"):
                zy = (h[r0 + 1 : e1 + 1] - h[r0:e1] - ty[r0:e1]) * np.sqrt(wy[r0:e1]) / k
            np.multiply(wy[r0:e1], np.where(cut_y[r0:e1], cauchy(zy), 1), out=out_y[r0:e1])

    run_blocks(block, range(0, rows, step), workers=workers)
    return out_x, out_y, out_f


def _bent_edges(gx, gy, step_sigma, s, *, k):
    """Edges where the normals themselves show a break: the only ones that may be cut.

    A real discontinuity leaves a trace in the normals — the straddling pixels mix both
    sides (or see a wall), so their slope differs from their neighbours' by far more than
    the noise: s·|g[c+1] − g[c−1]|/2 > k·(step noise) at either end, or no normal at all.
    On smooth ground the slopes are continuous, so an island of unwrapping errors cannot
    cut itself loose there: its fringe heights are re-weighted instead.
    """

    def bend(g, axis):
        d = np.zeros_like(g)
        if axis == 1:
            d[:, 1:-1] = np.abs(g[:, 2:] - g[:, :-2])
        else:
            d[1:-1, :] = np.abs(g[2:, :] - g[:-2, :])
        return d

    with np.errstate(invalid="ignore"):
        z = np.maximum(bend(gx, 1), bend(gy, 0)) * np.float32(s / 2) / step_sigma
    broken = ~(z <= k)  # NaN (no normal, no noise estimate) counts as broken
    return broken[:, 1:] | broken[:, :-1], broken[1:, :] | broken[:-1, :]


def _cut_discontinuities(f, sig_f, has_f, wx, wy, tx, ty, cut_x, cut_y, *, k, max_step):
    """Down-weight edges whose slope step contradicts the fringes' own step.

    A normal cannot express a height discontinuity (a cliff at a chip, the wall of a deep
    stroke seen edge-on): the pixel that straddles it mixes both sides and predicts a gentle
    step, and a stiff slope term then drags the lower side up (or the upper down) over many
    pixels. The fringe heights see the jump. An edge between two fringe heights that agree
    with their 3×3 median (so that an isolated unwrapping error does not cut its four edges)
    is compared with the fringes' step: r = (f_q − f_p) − t, σ_r² = σ_f,p² + σ_f,q² + 1/w
    (the crease model error is in σ_f); beyond k·σ_r its weight falls as (k·σ_r/r)². Only
    edges where the normals show a break (`_bent_edges`) are tested.
    """
    filled = np.where(has_f, f, np.float32(0))
    trusted = _step_consistent(filled, sig_f, has_f, wx, wy, tx, ty, k=k)
    var_f = np.where(trusted, np.square(sig_f), np.inf).astype(np.float32, copy=False)

    def cut(w, t, fa, fb, va, vb, allowed):
        with np.errstate(invalid="ignore", divide="ignore"):
            var = va + vb + np.where(w > 0, 1.0 / w, np.inf)
            r2 = np.square((fb - fa) - t)
            keep = np.minimum(1.0, k * k * var / r2)
        keep = np.where(np.isfinite(keep) & allowed, keep, 1).astype(np.float32, copy=False)
        return w * keep

    wx0, wy0 = wx, wy
    wx = cut(wx, tx, filled[:, :-1], filled[:, 1:], var_f[:, :-1], var_f[:, 1:], cut_x)
    wy = cut(wy, ty, filled[:-1, :], filled[1:, :], var_f[:-1, :], var_f[1:, :], cut_y)
    active = np.concatenate([wx0[wx0 > 0], wy0[wy0 > 0]])
    faint = np.float32(1e-3 * (float(fast_median(active)) if active.size else 1.0))
    wx, sx = _cut_through_untrusted(wx, wx0, tx, filled, var_f, cut_x, k, faint, max_step)
    wy, sy = _cut_through_untrusted(
        wy.T, wy0.T, ty.T, filled.T, var_f.T, cut_y.T, k, faint, max_step
    )
    return wx, wy.T, sx | sy.T


_MAX_SLOPE = float(np.tan(np.radians(60.0)))  # steepest ground the fusion treats as continuous


def _cut_through_untrusted(w, w0, t, f, var_f, allowed, k, faint, max_step):
    """Cut the in-line edges of an untrusted pixel that a cliff runs through.

    The pixels straddling a cliff (or at its foot, shadowed for every azimuth) have no
    fringe height, or one that fits neither side (the phases of both sides mix; the normal
    is flat on both), so their own edges cannot be tested, and their slope terms carry the
    cliff's pull from one side to the other over several pixels. The two-edge path over
    such a pixel is tested instead: its trusted neighbours along the row against the sum
    of the two targets, σ² = σ_f,a² + σ_f,b² + 1/w₁ + 1/w₂, and against what ground of the
    steepest slope the fusion treats as continuous (60°) can rise over two pixels,
    `max_step` per pixel (steep rims and strokes at coarse pixels are not cliffs). Beyond
    both the pixel is
    "stranded": both edges get the same faint weight and (by the caller) no fringe term, so
    it settles at the mean of its neighbours — between the sides, where the area mean of a
    straddling pixel lies — without pulling either side. Rows are axis 1.
    Returns (w, stranded (H, W) bool).
    """
    gap = np.zeros(f.shape, bool)
    gap[:, 1:-1] = ~np.isfinite(var_f[:, 1:-1])
    with np.errstate(invalid="ignore", divide="ignore"):
        var = (
            var_f[:, :-2]
            + var_f[:, 2:]
            + np.where(w0[:, :-1] > 0, 1 / w0[:, :-1], np.inf)
            + np.where(w0[:, 1:] > 0, 1 / w0[:, 1:], np.inf)
        )
        r2 = np.square(f[:, 2:] - f[:, :-2] - t[:, :-1] - t[:, 1:])
        broken = (r2 > k * k * var) & (r2 > np.square(2 * max_step))
    broken &= gap[:, 1:-1] & allowed[:, :-1] & allowed[:, 1:] & np.isfinite(var)
    w = w.copy()
    w[:, :-1] = np.where(broken, np.minimum(w[:, :-1], faint), w[:, :-1])
    w[:, 1:] = np.where(broken, np.minimum(w[:, 1:], faint), w[:, 1:])
    stranded = np.zeros(f.shape, bool)
    stranded[:, 1:-1] = broken
    return w, stranded


def _step_consistent(f, sig_f, has_f, wx, wy, tx, ty, *, k):
    """Fringe heights that agree with at least two of their four neighbours through the slopes.

    f_p is consistent with neighbour q when |f_q − f_p − t_pq| ≤ k·σ (σ² = σ_f,p² + σ_f,q² +
    1/w_pq). An isolated unwrapping error or spike agrees with none (a two-pixel one with at
    most one); a pixel on either side of a cliff, straight or staircase-diagonal, agrees with
    the two or more neighbours on its own side — on sloped ground too, where a 3×3 median of
    the raw heights would reject the pixels at the foot of the cliff.
    """
    var = np.where(has_f, np.square(sig_f), np.inf).astype(np.float32, copy=False)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_wx = np.where(wx > 0, 1.0 / wx, np.inf)
        inv_wy = np.where(wy > 0, 1.0 / wy, np.inf)
        okx = np.square(f[:, 1:] - f[:, :-1] - tx) <= k * k * (var[:, 1:] + var[:, :-1] + inv_wx)
        oky = np.square(f[1:, :] - f[:-1, :] - ty) <= k * k * (var[1:, :] + var[:-1, :] + inv_wy)
    okx &= np.isfinite(var[:, 1:]) & np.isfinite(var[:, :-1])
    oky &= np.isfinite(var[1:, :]) & np.isfinite(var[:-1, :])
    votes = np.zeros(f.shape, np.int8)
    votes[:, 1:] += okx
    votes[:, :-1] += okx
    votes[1:, :] += oky
    votes[:-1, :] += oky
    return has_f & (votes >= 2)


def _zero_mean_where_no_data(parts, h, mask, has_data):
    """h less its mean on each connected part of the mask (parts: ndimage.label(mask))
    that has no data."""
    labels, count = parts
    if count == 0:
        return h
    data_count = np.bincount(labels.ravel(), weights=has_data.ravel(), minlength=count + 1)
    if np.all(data_count[1:] > 0):
        return h  # every part has data: nothing to shift (h − 0 is h, bit for bit)
    sums, counts = _label_stats(np.where(mask, h, 0), labels, count)
    offset = np.where(data_count > 0, 0.0, sums / np.maximum(counts, 1)).astype(np.float32)
    offset[0] = 0
    return h - offset[labels]


def _bridge(w, both_in_mask, *targets):
    """Faint weight and flat targets on the mask's edges that have no weight: (w, *targets)."""
    active = w[w > 0]
    faint = np.float32(1e-3 * (float(fast_median(active)) if active.size else 1.0))
    gap = both_in_mask & ~(w > 0)
    return np.where(gap, faint, w), *(np.where(gap, np.float32(0), t) for t in targets)


def _edge_weight(wa, wb):
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 2.0 * wa * wb / (wa + wb)
    return np.where((wa > 0) & (wb > 0), w, 0).astype(np.float32, copy=False)


def _anchor_parts_without_data(parts, mask, lam, wx, wy):
    """Give a faint pull towards 0 to connected parts that no fringe height reaches.

    Such a part (a photometric-only bundle, or an island shadowed for every azimuth) is
    defined by its slopes up to a constant; the faint term fixes that constant at 0 mean
    without bending the surface (it is 1e-6 of the part's mean slope weight).
    parts: ndimage.label(mask).
    """
    labels, count = parts
    if count == 0:
        return lam
    has_data = np.bincount(labels.ravel(), weights=(lam > 0).ravel(), minlength=count + 1)[1:] > 0
    if np.all(has_data):
        return lam
    w_pix = np.zeros_like(lam)
    w_pix[:, 1:] += wx
    w_pix[1:, :] += wy
    scale = float(np.median(w_pix[mask & (w_pix > 0)])) if np.any(w_pix[mask] > 0) else 1.0
    missing = np.concatenate([[False], ~np.asarray(has_data, bool)])[labels]
    return np.where(missing, np.float32(scale * 1e-6), lam)


# Variance (px²) of a camera pixel's own footprint, a 1 × 1 px box: Var U(−½, ½) = 1/12 per axis.
PIXEL_AREA_VAR_PX2 = 1.0 / 12.0


def point_sample_sigma_px(camera_psf_px: float) -> float:
    """σ (px) of the Gaussian whose second-order blur equals the camera's: its PSF and the
    pixel's own area together, √(σ_psf² + 1/12).

    SCAN_BUNDLE.md: a pixel's height is the point sample at its centre, "not an average
    over the pixel or over the camera's blur". A pixel integrates the light over its area,
    so its normal is the slope of the surface averaged over a 1 px box (the cell-average
    targets of the fusion model exactly that), and the fused heights are the box average
    H = h + (1/24)∇²h + O(∇⁴h), the first step of the heat equation with σ² = 1/12. The box
    is the same for every camera (its variance is that of the pixel's footprint, whatever
    the optics); the PSF comes from the manifest (`camera.psf_sigma_px`) or is 0. Variances
    of independent blurs add. Measured on bench/robustness.py scans (wedge depth error,
    none → box): native-hard-512 19.6 → 18.4 µm, native-random-15 20.1 → 16.4,
    native-random-11 29.9 → 25.8 (docs/reconstruction.md).
    """
    if not camera_psf_px >= 0:
        raise ValueError(f"camera_psf_px must be >= 0, got {camera_psf_px}")
    return float(np.sqrt(float(camera_psf_px) ** 2 + PIXEL_AREA_VAR_PX2))


def sharpen_heights(
    height_um: np.ndarray,
    mask: np.ndarray,
    *,
    blur_sigma_px: float,
    pixel_size_um: float,
    max_slope: float = float(np.tan(np.radians(60.0))),
    significance: float = 3.0,
) -> np.ndarray:
    """Undo a Gaussian camera blur of σ px to second order: h ≈ h_b − (σ²/2)·∇²h_b.

    Images blurred by a Gaussian PSF give normals and fringe heights of the blurred surface,
    h_b = G_σ * h = h + (σ²/2)∇²h + O(σ⁴∇⁴h) (G_σ solves the heat equation ∂_t u = ½∇²u at
    t = σ², the scale-space of Lindeberg 1994; undoing it is one backward step). Its effect
    is concentrated where the surface bends sharply: wedge bottoms come out too shallow,
    rims too low. ∇² is the five-point Laplacian on the pixel grid,
    computed only where the four neighbours are on the mask (elsewhere no correction). On
    flat ground ∇²h_b is mostly noise, which the correction would amplify: it is shrunk by
    the non-negative garrote gain max(0, 1 − (k·σ_L/L)²) (Breiman 1995), σ_L the noise of L
    (1.4826·MAD over the mask), k = `significance`, so only bends well above the noise are
    sharpened and flat ground keeps its noise. The expansion holds for a continuous surface,
    whose slope turns by at most 2·`max_slope` across a pixel, i.e. |∇²h| ≤ 2·max_slope·s
    (µm per px²); beyond that (a cliff, a fringe outlier) the correction is clipped there
    instead of growing with the jump. A bend that no 4-neighbour shares (`_lone_bends`: an
    isolated outlier, which a blurred surface cannot hold) is left as it is.

    height_um: (H, W) µm, NaN off the mask; mask: (H, W) bool; blur_sigma_px ≥ 0.
    Returns (H, W) float32, NaN where height_um is.
    """
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool)
    if m.shape != h.shape:
        raise ValueError(f"mask shape {m.shape} does not match height_um {h.shape}")
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    if not blur_sigma_px >= 0:
        raise ValueError(f"blur_sigma_px must be >= 0, got {blur_sigma_px}")
    valid = m & np.isfinite(h)
    if blur_sigma_px == 0 or valid.sum() < 25:
        return h.copy()
    # Only the valid pixels' bounding box changes; its inner pixels in C order are the
    # whole frame's, so the noise estimate is the same.
    r0, r1, c0, c1 = _bbox(valid)
    box = (slice(r0, r1), slice(c0, c1))
    result = h.copy()
    result[box] = _sharpened(
        h[box], valid[box], blur_sigma_px, pixel_size_um, max_slope, significance
    )
    return result


def _lone_bends(lap: np.ndarray, significant: np.ndarray) -> np.ndarray:
    """Pixels whose significant bend no 4-neighbour shares (a significant Laplacian of the
    same sign): a point-like extremum narrower than a pixel both ways.

    A blurred surface's Laplacian is the blurred Laplacian of the surface, so a bend spreads
    over its neighbours along at least one direction: a wedge's floor or rim runs along a
    line. A single pixel whose Laplacian all four neighbours oppose is an isolated outlier of
    the fused heights (a one-pixel normal outlier integrates into such a dipole), which the
    backward heat step would double: there the data contradict the blur model and the
    sharpening stands down.
    """
    pos = significant & (lap > 0)
    neg = significant & (lap < 0)
    out = np.zeros_like(significant)
    for same in (pos, neg):
        shared = np.zeros_like(same)
        shared[1:, :] |= same[:-1, :]
        shared[:-1, :] |= same[1:, :]
        shared[:, 1:] |= same[:, :-1]
        shared[:, :-1] |= same[:, 1:]
        out |= same & ~shared
    return out


def _sharpened(h, valid, blur_sigma_px, pixel_size_um, max_slope, significance):
    """`sharpen_heights` on a box holding every valid pixel."""
    f = np.where(valid, h, 0).astype(np.float32, copy=False)
    inner = np.zeros_like(valid)
    inner[1:-1, 1:-1] = (
        valid[1:-1, 1:-1] & valid[:-2, 1:-1] & valid[2:, 1:-1] & valid[1:-1, :-2] & valid[1:-1, 2:]
    )
    lap = np.zeros_like(f)
    lap[1:-1, 1:-1] = f[:-2, 1:-1] + f[2:, 1:-1] + f[1:-1, :-2] + f[1:-1, 2:] - 4 * f[1:-1, 1:-1]
    lap = np.where(inner, lap, np.float32(0))
    sample = lap[inner][::3]  # a third of the values fixes the MAD to < 1 %
    if sample.size < 25:
        return h
    noise = 1.4826 * float(fast_median(np.abs(sample - fast_median(sample))))
    floor = np.float32(np.square(significance * noise))
    lap2 = np.square(lap)
    with np.errstate(invalid="ignore", divide="ignore"):
        gain = np.where(lap2 > floor, 1 - floor / lap2, np.float32(0))
    gain[_lone_bends(lap, lap2 > floor)] = 0
    limit = np.float32(2 * max_slope * pixel_size_um)
    out = h - np.float32(0.5 * blur_sigma_px**2) * np.clip(gain * lap, -limit, limit)
    return np.where(valid, out, h).astype(np.float32, copy=False)
