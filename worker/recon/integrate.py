"""Integration of surface slopes into heights on a masked pixel grid.

The one numerical core of stages 6 (normals alone) and the default fusion: a weighted
least-squares problem on the pixel grid,

    E(h) = Σ_x-edges wx (h[r, c+1] − h[r, c] − tx)² + Σ_y-edges wy (h[r+1, c] − h[r, c] − ty)²
         + Σ_pixels λ (h − d)²,

whose normal equations (a screened Poisson equation with variable coefficients) are solved by
conjugate gradients preconditioned with the constant-coefficient operator w̄·L + λ̄·I, where L
is the Neumann Laplacian, diagonalised by the type-II DCT (Simchony, Chellappa & Shao 1990,
"Direct analytical methods for solving Poisson equations in computer vision problems"; the
least-squares view of Quéau, Durou & Aujol 2018, "Normal integration: a survey").

Conventions (SCAN_BUNDLE.md): n ∝ (−∂h/∂x, −∂h/∂y, −1), hence ∂h/∂x = n_x/n_z and
∂h/∂y = n_y/n_z (dimensionless); x runs along columns, y along rows; h in µm.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import fft, ndimage

from worker.recon.arrays import fast_median
from worker.recon.parallel import run_blocks

__all__ = [
    "ScreenedPoisson",
    "edge_targets_um",
    "integrate_normals",
    "slopes_from_normals",
    "solve_screened_poisson",
]


def slopes_from_normals(normals: np.ndarray, *, min_abs_nz: float = 1e-3):
    """Slopes (∂h/∂x, ∂h/∂y) of the surface whose unit normals are given.

    normals: (H, W, 3) float, n_z < 0 (facing the camera); NaN allowed.
    Returns gx, gy: (H, W) float32, dimensionless; NaN where the normal is missing or
    |n_z| < min_abs_nz (a wall seen edge-on has no finite slope).
    """
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3), got {n.shape}")
    nz = n[..., 2].astype(np.float32)
    bad = ~(np.abs(nz) >= min_abs_nz)
    with np.errstate(invalid="ignore", divide="ignore"):
        gx = n[..., 0].astype(np.float32) / nz
        gy = n[..., 1].astype(np.float32) / nz
    gx[bad] = np.nan
    gy[bad] = np.nan
    return gx, gy


def edge_targets_um(gx: np.ndarray, gy: np.ndarray, *, pixel_size_um: float):
    """Height differences along grid edges predicted by per-pixel slopes (trapezoid rule).

    gx, gy: (H, W) dimensionless slopes. Returns tx (H, W−1) = s·(gx[:, c] + gx[:, c+1])/2 and
    ty (H−1, W) = s·(gy[r] + gy[r+1])/2 in µm (NaN where an endpoint is NaN).
    """
    s = float(pixel_size_um)
    tx = (gx[:, 1:] + gx[:, :-1]) * np.float32(0.5 * s)
    ty = (gy[1:, :] + gy[:-1, :]) * np.float32(0.5 * s)
    return tx, ty


@dataclass(frozen=True)
class ScreenedPoisson:
    """Result of `solve_screened_poisson`: heights (H, W) float32 µm, iterations, residual."""

    height_um: np.ndarray
    iterations: int
    relative_residual: float


# Rows of `_apply`'s blocks hold about this many pixels: the block's five arrays and two
# temporaries stay in the core's cache instead of streaming whole frames through memory.
_APPLY_BLOCK_PX = 131_072


def _apply(h, wx, wy, lam, workers=1):
    """A·h for A = Dxᵀ Wx Dx + Dyᵀ Wy Dy + diag(λ).

    Per pixel λh + e_left − e_right + e_up − e_down in that order, computed in blocks of
    rows (shared out between `workers` threads): each block takes the y-edges on its
    borders itself, so every value is that of the whole-frame formula.
    """
    rows, cols = h.shape
    out = np.empty_like(h)
    step = max(1, _APPLY_BLOCK_PX // cols)

    def block(r0):
        r1 = min(r0 + step, rows)
        o = out[r0:r1]
        np.multiply(lam[r0:r1], h[r0:r1], out=o)
        ex = wx[r0:r1] * (h[r0:r1, 1:] - h[r0:r1, :-1])
        o[:, 1:] += ex
        o[:, :-1] -= ex
        # y-edges e0 … e1 − 1 (edge e joins rows e and e + 1) reach the rows r0 … r1 − 1.
        e0, e1 = max(r0 - 1, 0), min(r1, rows - 1)
        ey = wy[e0:e1] * (h[e0 + 1 : e1 + 1] - h[e0:e1])
        first = max(r0, 1)  # rows from here on gain the edge above them
        o[first - r0 :] += ey[first - 1 - e0 : r1 - 1 - e0]
        o[: e1 - r0] -= ey[r0 - e0 :]

    run_blocks(block, range(0, rows, step), workers=workers)
    return out


def _rhs(tx, ty, wx, wy, lam, data):
    b = lam * data
    ex = wx * tx
    b[:, 1:] += ex
    b[:, :-1] -= ex
    ey = wy * ty
    b[1:, :] += ey
    b[:-1, :] -= ey
    return b


def _dct_preconditioner(shape, w_bar, lam_bar, workers=1):
    rows, cols = shape
    ky = 2.0 - 2.0 * np.cos(np.pi * np.arange(rows) / rows)
    kx = 2.0 - 2.0 * np.cos(np.pi * np.arange(cols) / cols)
    # w̄·(k_y + k_x) + λ̄ and its inverse (0 where it vanishes) in place: whole-frame float64
    # temporaries cost more in page faults than in arithmetic.
    denom = ky[:, None] + kx[None, :]
    denom *= w_bar
    denom += lam_bar
    positive = denom > 0
    np.divide(1.0, denom, out=denom, where=positive)
    denom[~positive] = 0
    inv = denom.astype(np.float32)

    def apply(r, overwrite=False):
        # The 1-D transforms of each axis are independent: threads give the same values.
        c = fft.dctn(r, norm="ortho", overwrite_x=overwrite, workers=workers)
        c *= inv
        return fft.idctn(c, norm="ortho", overwrite_x=True, workers=workers)

    return apply


def solve_screened_poisson(
    tx: np.ndarray,
    ty: np.ndarray,
    wx: np.ndarray,
    wy: np.ndarray,
    *,
    data_um: np.ndarray | None = None,
    data_weight: np.ndarray | None = None,
    x0_um: np.ndarray | None = None,
    rtol: float = 1e-4,
    max_iter: int = 500,
    workers: int = 1,
) -> ScreenedPoisson:
    """Minimise E(h) (module docstring) by DCT-preconditioned conjugate gradients.

    tx: (H, W−1) µm target differences h[r, c+1] − h[r, c]; wx: same shape, weights ≥ 0.
    ty: (H−1, W) µm targets for h[r+1, c] − h[r, c]; wy: same shape.
    data_um: (H, W) µm target heights (ignored where data_weight is 0); data_weight: (H, W) λ ≥ 0.
    A pixel with no edge and no data weight is unconstrained: it is returned as 0.
    Without data (λ ≡ 0) heights are defined up to a constant per connected part; the
    solution returned has the minimum norm for the preconditioned iteration (mean ≈ 0).
    workers: threads of the DCTs (the result does not depend on it).
    """
    wx = np.asarray(wx, dtype=np.float32)
    wy = np.asarray(wy, dtype=np.float32)
    rows, cols = wy.shape[0] + 1, wx.shape[1] + 1
    if wx.shape != (rows, cols - 1) or np.shape(tx) != wx.shape:
        raise ValueError(f"tx and wx must have shape {(rows, cols - 1)}")
    if wy.shape != (rows - 1, cols) or np.shape(ty) != wy.shape:
        raise ValueError(f"ty and wy must have shape {(rows - 1, cols)}")
    if np.any(wx < 0) or np.any(wy < 0):
        raise ValueError("wx and wy must be non-negative")
    if data_weight is not None:
        lam_in = np.asarray(data_weight, np.float32)
        if lam_in.shape != (rows, cols) or data_um is None or np.shape(data_um) != (rows, cols):
            raise ValueError(f"data_um and data_weight must have shape {(rows, cols)}")
        if np.any(lam_in < 0):
            raise ValueError("data_weight must be non-negative")
    else:
        lam_in = None
    tx, ty, wx, wy, lam, data, h = _solver_inputs(
        np.asarray(tx),
        np.asarray(ty),
        wx,
        wy,
        None if lam_in is None else np.asarray(data_um),
        lam_in,
        None if x0_um is None else np.asarray(x0_um),
        workers=workers,
    )
    h, it, res = _solve_prepared(tx, ty, wx, wy, lam, data, h, rtol, max_iter, workers)
    if h.shape != (rows, cols):
        h = h[:rows, :cols].copy()
    return ScreenedPoisson(height_um=h, iterations=it, relative_residual=res)


# Rows of `_solver_inputs`' blocks hold about this many pixels (seven arrays in, seven out).
_PREPARE_BLOCK_PX = 65_536


def _solver_inputs(tx, ty, wx, wy, data_um, data_weight, x0_um, *, workers=1):
    """The solver's own float32 copies of its inputs, on the grid padded to lengths the
    DCT is fast on (the pad: unconstrained pixels, 0 everywhere, a separate block of the
    system; cropped off at the end). Targets, data and start heights are cleaned by
    `_clean_into` (0 where their weight is 0). Filled in blocks of rows shared out between
    `workers` threads, elementwise: the values of whole-frame passes.
    Returns (tx, ty, wx, wy, lam, data, h0).
    """
    rows, cols = wy.shape[0] + 1, wx.shape[1] + 1
    fast_rows, fast_cols = fft.next_fast_len(rows, real=True), fft.next_fast_len(cols, real=True)
    lam_p, data_p, h_p = (np.zeros((fast_rows, fast_cols), np.float32) for _ in range(3))
    wx_p, tx_p = (np.zeros((fast_rows, fast_cols - 1), np.float32) for _ in range(2))
    wy_p, ty_p = (np.zeros((fast_rows - 1, fast_cols), np.float32) for _ in range(2))
    step = max(1, _PREPARE_BLOCK_PX // cols)

    def block(r0):
        r1 = min(r0 + step, rows)
        rb = slice(r0, r1)
        wx_p[rb, : cols - 1] = wx[rb]
        _clean_into(tx_p[rb, : cols - 1], tx[rb], wx[rb] > 0)
        yb = slice(r0, min(r1, rows - 1))  # y-edge e joins rows e and e + 1
        wy_p[yb, :cols] = wy[yb]
        _clean_into(ty_p[yb, :cols], ty[yb], wy[yb] > 0)
        if data_weight is not None:
            lam_p[rb, :cols] = data_weight[rb]
            _clean_into(data_p[rb, :cols], data_um[rb], lam_p[rb, :cols] > 0)
        if x0_um is not None:
            _clean_into(h_p[rb, :cols], x0_um[rb])

    run_blocks(block, range(0, rows, step), workers=workers)
    return tx_p, ty_p, wx_p, wy_p, lam_p, data_p, h_p


def _clean_into(out, values, keep=None):
    """values copied into the float32 `out` where keep (out keeps its 0 elsewhere), then
    np.nan_to_num'ed in place (NaN → 0, ±inf → ±the largest float32); its passes only when a
    value is not finite."""
    np.copyto(out, np.asarray(values), where=True if keep is None else keep)
    if not np.isfinite(out).all():
        np.nan_to_num(out, copy=False)


def _solve_prepared(tx, ty, wx, wy, lam, data, h, rtol, max_iter, workers):
    """`solve_screened_poisson` on the inputs of `_solver_inputs` (which it modifies):
    (heights, iterations, relative residual)."""
    rows, cols = h.shape
    deg = lam.copy()
    deg[:, 1:] += wx
    deg[:, :-1] += wx
    deg[1:, :] += wy
    deg[:-1, :] += wy
    free = deg <= 0
    constrained = ~free
    # A typical edge weight for the preconditioner; a sample of the weights is enough.
    active_w = np.concatenate([wx.ravel()[::7], wy.ravel()[::7]])
    active_w = active_w[active_w > 0]
    w_bar = float(fast_median(active_w)) if active_w.size else 1.0
    lam_bar = float(lam[constrained].mean()) if constrained.any() else 0.0
    pure_neumann = lam_bar == 0.0
    # Pixels that no term touches (off the mask) form a separate block of the system; giving
    # them the preconditioner's own operator (membrane w̄ to each other, screening λ̄ towards 0)
    # keeps A close to w̄·L + λ̄·I so that CG converges in a few iterations.
    if free.any():
        np.copyto(wx, np.float32(w_bar), where=free[:, 1:] & free[:, :-1])
        np.copyto(wy, np.float32(w_bar), where=free[1:, :] & free[:-1, :])
        np.copyto(lam, np.float32(lam_bar if lam_bar > 0 else w_bar * 1e-3), where=free)
    dct_solve = _dct_preconditioner((rows, cols), w_bar, lam_bar, workers)
    # Symmetric diagonal scaling around the DCT solve, S·P·S with S = √(d̄/d) (d the diagonal
    # of A, d̄ the constant operator's): where walls are down-weighted or fringe heights
    # rejected, A's local stiffness differs from w̄·L + λ̄·I by orders of magnitude, and the
    # scaling restores it to first order.
    diag = lam.copy()
    diag[:, 1:] += wx
    diag[:, :-1] += wx
    diag[1:, :] += wy
    diag[:-1, :] += wy
    d_bar = np.float32(4.0 * w_bar + lam_bar)
    scale = np.sqrt(d_bar / np.maximum(diag, d_bar * 1e-6)).astype(np.float32, copy=False)

    if lam_bar < 1e-4 * w_bar:
        # Nearly pure Poisson (normals alone): the smooth modes dominate, which the plain DCT
        # solve captures and the diagonal scaling would distort.
        precond = dct_solve
    else:

        def precond(r):
            z = dct_solve(scale * r, overwrite=True)
            z *= scale
            return z

    b = _rhs(tx, ty, wx, wy, lam, data)
    r = b - _apply(h, wx, wy, lam, workers)
    b_norm = float(np.linalg.norm(b)) or 1.0
    z = precond(r)
    if pure_neumann:
        z -= z.mean()
    p = z.copy()
    rz = float(np.vdot(r, z))
    it = 0
    res = float(np.linalg.norm(r)) / b_norm
    while res > rtol and it < max_iter:
        ap = _apply(p, wx, wy, lam, workers)
        pap = float(np.vdot(p, ap))
        if pap <= 0:
            break
        alpha = rz / pap
        h += np.float32(alpha) * p
        r -= np.float32(alpha) * ap
        z = precond(r)
        if pure_neumann:
            z -= z.mean()
        rz_new = float(np.vdot(r, z))
        p = z + np.float32(rz_new / rz) * p
        rz = rz_new
        it += 1
        res = float(np.linalg.norm(r)) / b_norm
    h[free] = 0
    return h, it, res


def _label_stats(values, labels, count):
    """Per-label sums and counts (labels 1..count) via bincount: ndimage's are much slower."""
    lab = labels.ravel()
    sums = np.bincount(lab, weights=np.asarray(values, np.float64).ravel(), minlength=count + 1)
    counts = np.bincount(lab, minlength=count + 1)
    return sums, counts


def masked_edge_weights(mask: np.ndarray, weight: np.ndarray | None = None):
    """Edge weights (H, W−1), (H−1, W): the smaller pixel weight of the two ends, 0 off the mask."""
    m = np.asarray(mask, bool)
    w = m.astype(np.float32) if weight is None else np.where(m, weight, 0).astype(np.float32)
    wx = np.minimum(w[:, 1:], w[:, :-1])
    wy = np.minimum(w[1:, :], w[:-1, :])
    return wx, wy


def integrate_normals(
    normals: np.ndarray, *, pixel_size_um: float, mask: np.ndarray, rtol: float = 1e-5
) -> np.ndarray:
    """Heights whose gradient best fits the normals in the least-squares sense, on the mask.

    normals: (H, W, 3) unit normals facing the camera (n_z < 0), NaN allowed.
    pixel_size_um: lateral sampling s > 0. mask: (H, W) bool, pixels to reconstruct.
    Returns (H, W) float32 heights in µm, NaN off the mask; each connected part of the mask
    is defined up to a constant, which is chosen so that its mean height is 0.
    Slopes of pixels with |n_z| < 0.05 (walls steeper than ~87°) are left out.
    """
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    m = np.asarray(mask, bool)
    if m.shape != np.shape(normals)[:2]:
        raise ValueError(f"mask shape {m.shape} does not match normals {np.shape(normals)}")
    out = np.full(m.shape, np.nan, np.float32)
    if not m.any():
        return out
    r0, r1, c0, c1 = _bbox(m)
    m_c = m[r0:r1, c0:c1]
    gx, gy = slopes_from_normals(np.asarray(normals)[r0:r1, c0:c1], min_abs_nz=0.05)
    valid = m_c & np.isfinite(gx) & np.isfinite(gy)
    tx, ty = edge_targets_um(gx, gy, pixel_size_um=pixel_size_um)
    # Masked pixels without a usable normal are bridged by a weak membrane (target 0) so that
    # they neither float free nor pull on the slopes around them.
    wx, wy = masked_edge_weights(m_c, np.where(valid, np.float32(1), np.float32(1e-2)))
    x0 = _coarse_guess(gx, gy, m_c, pixel_size_um, rtol)
    sol = solve_screened_poisson(tx, ty, wx, wy, x0_um=x0, rtol=rtol, max_iter=2000)
    h = _zero_mean_per_component(sol.height_um, m_c)
    out[r0:r1, c0:c1] = np.where(m_c, h, np.nan)
    return out


def _coarse_guess(gx, gy, mask, pixel_size_um, rtol):
    """Cascadic initial guess: the same problem solved on a grid twice as coarse, upsampled.

    The DCT preconditioner is exact only for a rectangle; on a ragged mask the smooth,
    long-wavelength error is what CG resolves slowly, and a coarse grid removes it cheaply.
    """
    rows, cols = mask.shape
    if min(rows, cols) < 64:
        return None
    r2, c2 = rows // 2 * 2, cols // 2 * 2

    m_blocks = mask[:r2, :c2].reshape(r2 // 2, 2, c2 // 2, 2)
    m2 = m_blocks.sum(axis=(1, 3)) >= 2
    gx_m = np.where(mask, gx, np.nan)[:r2, :c2].reshape(m_blocks.shape)
    gy_m = np.where(mask, gy, np.nan)[:r2, :c2].reshape(m_blocks.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        gx2 = np.nanmean(gx_m, axis=(1, 3)).astype(np.float32)
        gy2 = np.nanmean(gy_m, axis=(1, 3)).astype(np.float32)
    valid2 = m2 & np.isfinite(gx2) & np.isfinite(gy2)
    tx2, ty2 = edge_targets_um(gx2, gy2, pixel_size_um=2 * pixel_size_um)
    wx2, wy2 = masked_edge_weights(m2, np.where(valid2, np.float32(1), np.float32(1e-2)))
    x0 = _coarse_guess(gx2, gy2, m2, 2 * pixel_size_um, rtol)
    h2 = solve_screened_poisson(tx2, ty2, wx2, wy2, x0_um=x0, rtol=rtol, max_iter=2000).height_um
    up = cv2.resize(h2, (c2, r2), interpolation=cv2.INTER_LINEAR)
    out = np.zeros((rows, cols), np.float32)
    out[:r2, :c2] = up
    return out


def _bbox(mask):
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return rows[0], rows[-1] + 1, cols[0], cols[-1] + 1


def _zero_mean_per_component(h, mask):
    labels, n = ndimage.label(mask)
    if n == 0:
        return h
    sums, counts = _label_stats(np.where(mask, h, 0), labels, n)
    offset = (sums / np.maximum(counts, 1)).astype(np.float32)
    offset[0] = 0
    return h - offset[labels]
