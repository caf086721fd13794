"""The fusion of Kumar et al. 2003 (§3.3), "Digital Preservation of Ancient Cuneiform Tablets
Using 3D-Scanning" (3DIM 2003), as we read it (the text of Eqs. 6–12 was not available to us;
docs/reconstruction.md records this reading):

1. Initial guess: the image is cut into 4×4 blocks; in each block the heights are the least-
   squares fit to the slopes in the Fried geometry (D. L. Fried, JOSA 67, 1977): the slope of
   each 2×2 cell is the mean of its four pixels' slopes, and the model of a cell's slope is
   the mean of its two edge differences, gx ≈ ((h01 − h00) + (h11 − h10)) / 2 (along x) and
   gy ≈ ((h10 − h00) + (h11 − h01)) / 2 (along y). The fit is the minimum-norm one (no piston,
   no waffle); each block is then lifted so that its mean equals the block's mean fringe height.
2. Update (Eqs. 6–12 as read): every pixel moves to the λ-weighted mix of the height that its
   four neighbours predict through the slopes and the 5×5 median of the fringe heights,
       h ← (1 − λ)·mean_q(h_q + s·(g_p + g_q)/2 · d_pq) + λ·median5(f),
   a Jacobi sweep on the quadratic energy of both misfits; λ (Eq. 8) is the share of the
   fringe height in the estimate, λ = σ_n² / (σ_n² + σ_f²) with σ_n the height noise that the
   normals give over one pixel step and σ_f the fringe height noise.
3. Stop when the mean adjustment is under a hundredth of a pixel (0.01·s µm) after at least
   10 iterations.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from worker.recon.integrate import slopes_from_normals

__all__ = ["fried_block_heights", "fuse_paper", "fried_block_matrix", "paper_lambda"]

_BLOCK = 4


def fried_block_matrix(block: int = _BLOCK) -> np.ndarray:
    """Least-squares reconstructor of a block×block patch from its cells' slopes (Fried 1977).

    Returns (block², 2·(block−1)²) float64: heights (row-major, in units of pixel step × slope)
    from the stacked cell slopes [gx cells (row-major), gy cells (row-major)]; minimum norm, so
    the patch mean is 0 and the waffle mode is absent.
    """
    n = block
    cells = (n - 1) * (n - 1)
    g = np.zeros((2 * cells, n * n))
    for i in range(n - 1):
        for j in range(n - 1):
            k = i * (n - 1) + j
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            g[k, [a, b, c, d]] = [-0.5, 0.5, -0.5, 0.5]
            g[cells + k, [a, b, c, d]] = [-0.5, -0.5, 0.5, 0.5]
    return np.linalg.pinv(g)


def fried_block_heights(
    gx: np.ndarray, gy: np.ndarray, *, pixel_size_um: float, block_mean_um: np.ndarray
) -> np.ndarray:
    """Step 1: heights of each 4×4 block from its slopes, lifted to the given block means.

    gx, gy: (H, W) slopes (NaN → 0), H and W multiples of 4. block_mean_um: (H/4, W/4).
    Returns (H, W) float32 µm.
    """
    rows, cols = gx.shape
    if rows % _BLOCK or cols % _BLOCK:
        raise ValueError(f"gx shape {gx.shape} must be a multiple of {_BLOCK}")
    br, bc = rows // _BLOCK, cols // _BLOCK

    def cells(g):
        blocks = np.nan_to_num(g).reshape(br, _BLOCK, bc, _BLOCK).transpose(0, 2, 1, 3)
        cell = 0.25 * (
            blocks[..., :-1, :-1]
            + blocks[..., 1:, :-1]
            + blocks[..., :-1, 1:]
            + blocks[..., 1:, 1:]
        )
        return cell.reshape(br, bc, -1)

    slopes = np.concatenate([cells(gx), cells(gy)], axis=-1) * pixel_size_um
    h = np.einsum("ij,abj->abi", fried_block_matrix(), slopes)
    h = h.reshape(br, bc, _BLOCK, _BLOCK) + block_mean_um[:, :, None, None]
    return h.transpose(0, 2, 1, 3).reshape(rows, cols).astype(np.float32)


def paper_lambda(*, normal_sigma_rad: float, height_sigma_um: float, pixel_size_um: float) -> float:
    """λ of Eq. 8 (as read): the fringe share σ_n² / (σ_n² + σ_f²), σ_n = s·σ_θ per step."""
    sn2 = (pixel_size_um * normal_sigma_rad) ** 2
    return float(sn2 / (sn2 + height_sigma_um**2))


def fuse_paper(
    normals: np.ndarray,
    fringe_height_um: np.ndarray,
    *,
    pixel_size_um: float,
    mask: np.ndarray,
    normal_sigma_rad: float,
    height_sigma_um: float,
    min_iterations: int = 10,
    max_iterations: int = 2000,
) -> tuple[np.ndarray, int]:
    """Kumar et al. 2003 fusion (module docstring). Returns (height (H, W) float32 µm NaN off
    the mask, iterations). normals: (H, W, 3); fringe_height_um: (H, W) NaN where none;
    mask: (H, W) bool; the two sigmas are scalars > 0 (the paper uses one λ for the image).
    """
    n = np.asarray(normals)
    f = np.asarray(fringe_height_um, np.float32)
    m = np.asarray(mask, bool)
    if n.ndim != 3 or n.shape[2] != 3 or f.shape != n.shape[:2] or m.shape != f.shape:
        raise ValueError("normals (H, W, 3), fringe_height_um (H, W) and mask (H, W) must agree")
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    if not (normal_sigma_rad > 0 and height_sigma_um > 0):
        raise ValueError("normal_sigma_rad and height_sigma_um must be > 0")
    s = float(pixel_size_um)
    rows, cols = f.shape
    pr, pc = (-rows) % _BLOCK, (-cols) % _BLOCK
    gx, gy = slopes_from_normals(n, min_abs_nz=0.05)
    ok_g = m & np.isfinite(gx) & np.isfinite(gy)
    gx = np.where(ok_g, gx, 0).astype(np.float32)
    gy = np.where(ok_g, gy, 0).astype(np.float32)
    has_f = m & np.isfinite(f)
    fill = float(np.median(f[has_f])) if has_f.any() else 0.0
    f_med = ndimage.median_filter(np.where(has_f, f, fill), size=5, mode="nearest")
    f_med = np.where(has_f, f_med, np.nan).astype(np.float32)

    pad = ((0, pr), (0, pc))
    gxp, gyp = np.pad(gx, pad), np.pad(gy, pad)
    fp = np.pad(np.where(has_f, f_med, np.nan), pad, constant_values=np.nan)
    blocks = fp.reshape((rows + pr) // _BLOCK, _BLOCK, (cols + pc) // _BLOCK, _BLOCK)
    count = np.isfinite(blocks).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        bmean = np.nansum(blocks, axis=(1, 3)) / count
    bmean = np.where(count > 0, bmean, fill)
    h = fried_block_heights(gxp, gyp, pixel_size_um=s, block_mean_um=bmean)[:rows, :cols]

    lam = paper_lambda(
        normal_sigma_rad=normal_sigma_rad, height_sigma_um=height_sigma_um, pixel_size_um=s
    )
    lam_map = np.where(has_f, np.float32(lam), np.float32(0))
    target = np.where(has_f, f_med, 0).astype(np.float32)
    # Neighbour q of p predicts h_p = h_q + (h_p − h_q) from the mean slope of the two pixels.
    ex = (m[:, 1:] & m[:, :-1]).astype(np.float32)
    ey = (m[1:, :] & m[:-1, :]).astype(np.float32)
    dx = 0.5 * s * (gx[:, 1:] + gx[:, :-1])
    dy = 0.5 * s * (gy[1:, :] + gy[:-1, :])
    deg = np.zeros_like(h)
    deg[:, 1:] += ex
    deg[:, :-1] += ex
    deg[1:, :] += ey
    deg[:-1, :] += ey
    tol = 0.01 * s
    it = 0
    while it < max_iterations:
        acc = np.zeros_like(h)
        acc[:, 1:] += ex * (h[:, :-1] + dx)
        acc[:, :-1] += ex * (h[:, 1:] - dx)
        acc[1:, :] += ey * (h[:-1, :] + dy)
        acc[:-1, :] += ey * (h[1:, :] - dy)
        with np.errstate(invalid="ignore", divide="ignore"):
            pred = np.where(deg > 0, acc / deg, h)
        new = np.where(deg > 0, (1 - lam_map) * pred + lam_map * target, np.where(has_f, target, h))
        adjust = float(np.mean(np.abs(new - h)[m])) if m.any() else 0.0
        h = new
        it += 1
        if it >= min_iterations and adjust < tol:
            break
    return np.where(m, h, np.nan).astype(np.float32), it
