"""Low-frequency bias of photometric normals, corrected with the fringe heights.

Photometric normals are precise from pixel to pixel but can carry a bias that their
residuals do not show: an ambient or stray-light term common to all lights cannot be told
apart from n_z when the lights share one polar angle (it scales the slopes), and a broad
specular lobe tilts normals towards the lights. Such a bias is a smooth function of the
orientation, so it is correlated over whole regions of the surface — where the fringe
heights, noisy from pixel to pixel, are precise. Nehab, Rusinkiewicz, Davis & Ramamoorthi
2005 ("Efficiently combining positions and normals for precise 3D geometry", §4) correct it
before combining: the normals of the positions and the measured normals are smoothed with
the same Gaussian, and each measured normal is rotated by the rotation that takes its
smoothed measured normal to the smoothed positional normal. The measured normals keep their
fine detail and take their low frequencies from the positions.
"""

from __future__ import annotations

import cv2
import numpy as np

from worker.recon.arrays import fast_median

__all__ = ["correct_normal_bias", "correct_normals_to_positions", "correction_scale_px"]

# Noise gain of a Gaussian derivative: white noise of unit variance smoothed by a Gaussian of
# σ px has slopes of variance 1/(8π σ⁴) px⁻² per component (∫ k_x² e^{−σ²|k|²} d²k / 4π²).
_DOG_NOISE = 1.0 / np.sqrt(8.0 * np.pi)


def correction_scale_px(
    height_sigma_um: float, *, pixel_size_um: float, tolerance_rad: float
) -> float:
    """Gaussian σ (px) at which the heights' normals are precise to `tolerance_rad`.

    Heights with white noise σ_h, smoothed by a Gaussian of σ px, have slopes with noise
    σ_h/(s·σ²·√(8π)) per component; the scale returned makes that equal to
    `tolerance_rad`: σ = √(σ_h/(s·tol·√(8π))), at least 1 px. σ_h not finite or ≤ 0 → 1.
    """
    if not pixel_size_um > 0 or not tolerance_rad > 0:
        raise ValueError("pixel_size_um and tolerance_rad must be > 0")
    if not np.isfinite(height_sigma_um) or height_sigma_um <= 0:
        return 1.0
    return float(max(1.0, np.sqrt(height_sigma_um * _DOG_NOISE / (pixel_size_um * tolerance_rad))))


def correct_normal_bias(
    normals: np.ndarray,
    height_um: np.ndarray,
    *,
    pixel_size_um: float,
    mask: np.ndarray,
    height_sigma_um: np.ndarray | float,
    floor_rad: float,
) -> np.ndarray:
    """`correct_normals_to_positions` at the scale the data set, for the default fusion.

    Scale (`correction_scale_px`): where the heights' normals are precise to a fifth of
    `floor_rad` — the bias the normals' noise model allows for (`quality.NORMAL_FLOOR_RAD`)
    — so that the correction adds under 4 % of that variance. σ_h is the median of
    `height_sigma_um` on the mask: the fusion's σ map of the fringe heights, their noise
    and the crease term (how far a pixel's height can be from the surface at its centre;
    the phase noise alone, `Measurements.fringe_sigma_um`, is half of it on the quick
    preset and put the scale at 1.6 px, where wedges are as wide as the window and the
    rotation took the fringes' rounded wedges into the normals). A median rotation within
    3·`floor_rad` leaves the normals alone; `height_sigma_um` also weights the smoothing.
    """
    m = np.asarray(mask, bool)
    sig = np.broadcast_to(np.asarray(height_sigma_um, np.float32), m.shape)
    ok = m & np.isfinite(sig) & (sig > 0)
    sigma_h = float(fast_median(sig[ok])) if ok.any() else float("nan")
    scale = correction_scale_px(sigma_h, pixel_size_um=pixel_size_um, tolerance_rad=floor_rad / 5)
    return correct_normals_to_positions(
        normals,
        height_um,
        pixel_size_um=pixel_size_um,
        mask=m,
        sigma_px=scale,
        height_sigma_um=sig,
        bias_floor_rad=floor_rad,
    )


def correct_normals_to_positions(
    normals: np.ndarray,
    height_um: np.ndarray,
    *,
    pixel_size_um: float,
    mask: np.ndarray,
    sigma_px: float,
    height_sigma_um: np.ndarray | float | None = None,
    bias_floor_rad: float = 0.0,
    significance: float = 3.0,
    outlier_sigmas: float = 5.0,
    min_support: float = 0.25,
) -> np.ndarray:
    """Rotate each measured normal so that its low frequencies are those of the heights.

    Nehab et al. 2005 §4: n_p (positional, from central differences of `height_um`) and the
    measured n_m are smoothed by the same normalised Gaussian of `sigma_px`, with the same
    weights, renormalised to n̄_p and n̄_m, and n_m is rotated about n̄_m × n̄_p by their
    angle θ (Rodrigues). Weights: 1/σ_h² of each height relative to the typical one, capped
    at 1 (`height_sigma_um`, e.g. the fringe noise with the crease term, so that wedge rims
    and bottoms, where a height is the pixel's area mean, count little), on the support —
    mask pixels where both normals exist and their angle is not an outlier (beyond the
    median + `outlier_sigmas`·1.4826·MAD: cliffs, which the heights see and the normals do
    not, and unwrapping errors). The bias belongs to the set-up (lights, material), not to a
    pixel, so the correction is all or nothing: when the median θ over the support is
    within k·σ_b, σ_b² = `bias_floor_rad`² + the smoothed heights' slope noise²
    (σ_h/(s·σ²·√(8π)), σ_h the median of `height_sigma_um`; k = `significance`), the
    disagreement is within what the normals' noise model allows for and is left to the
    fusion's weights (on the simulator's `default` noise the median θ is 3.5 mrad, and
    rotating by it only moved the wedges towards the fringes' rounded ones; on `hard`,
    40 mrad). Where the Gaussian window holds less than `min_support` of full
    weight, θ fades in proportionally (the mask's rim); outside the support the normals are
    rotated with their neighbourhood's θ.

    normals: (H, W, 3) unit, n_z < 0, NaN where none. height_um: (H, W) µm, NaN where none.
    Returns (H, W, 3) float32 unit normals, NaN where `normals` is.
    """
    n = np.asarray(normals, np.float32)
    f = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3), got {n.shape}")
    if f.shape != n.shape[:2] or m.shape != f.shape:
        raise ValueError(f"height_um {f.shape} and mask {m.shape} must match normals {n.shape}")
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    out = n.copy()
    if not m.any():
        return out
    rows = np.flatnonzero(m.any(axis=1))
    cols = np.flatnonzero(m.any(axis=0))
    # The mask's bounding box, with room for the Gaussian's reach.
    pad = int(np.ceil(3 * sigma_px)) + 1
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, m.shape[0])
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, m.shape[1])
    crop = (slice(r0, r1), slice(c0, c1))
    sig = None
    if height_sigma_um is not None:
        sig = np.broadcast_to(np.asarray(height_sigma_um, np.float32), f.shape)[crop]
    out[crop] = _correct(
        n[crop],
        f[crop],
        m[crop],
        float(pixel_size_um),
        float(sigma_px),
        sig,
        float(bias_floor_rad),
        float(significance),
        float(outlier_sigmas),
        float(min_support),
    )
    return out


def _correct(n, f, m, s, sigma_px, sig, bias_floor_rad, significance, outlier_sigmas, min_support):
    nx, ny, nz = (np.ascontiguousarray(n[..., i]) for i in range(3))
    fm = np.where(m, f, np.float32(np.nan))
    # Positional normal ∝ (−∂h/∂x, −∂h/∂y, −1) from central differences.
    px = np.full(f.shape, np.nan, np.float32)
    py = np.full(f.shape, np.nan, np.float32)
    px[:, 1:-1] = (fm[:, 2:] - fm[:, :-2]) / np.float32(2 * s)
    py[1:-1, :] = (fm[2:, :] - fm[:-2, :]) / np.float32(2 * s)
    inv = 1 / np.sqrt(1 + px * px + py * py)
    qx, qy, qz = -px * inv, -py * inv, -inv
    support = m & np.isfinite(nx) & np.isfinite(ny) & np.isfinite(nz) & np.isfinite(inv)
    out = n.copy()
    if support.sum() < 25:
        return out
    # The chord |n − p| = 2 sin(angle/2) stands for the angle between the two normals (the
    # test only ranks them); a quarter of the pixels fix its median and MAD to ~1 %.
    chord = np.sqrt(
        np.square(nx[support] - qx[support])
        + np.square(ny[support] - qy[support])
        + np.square(nz[support] - qz[support])
    )
    sample = chord[::4]
    med = float(fast_median(sample))
    limit = med + outlier_sigmas * 1.4826 * float(fast_median(np.abs(sample - med)))
    support[support] = chord <= limit

    weight, sigma_h = _weights(support, sig)
    k = 2 * int(np.ceil(4 * sigma_px)) + 1

    def blur(v):
        return cv2.GaussianBlur(v, (k, k), sigma_px, borderType=cv2.BORDER_CONSTANT)

    ax_, ay_, az_, bx, by, bz = (
        blur(np.where(support, v * weight, np.float32(0))) for v in (nx, ny, nz, qx, qy, qz)
    )
    w = blur(weight)
    # Rotation axis c = ā × b̄ and angle θ = atan2(|c|, ā·b̄) of the two smoothed normals
    # (their lengths cancel in the angle).
    cx = ay_ * bz - az_ * by
    cy = az_ * bx - ax_ * bz
    cz = ax_ * by - ay_ * bx
    cn = np.sqrt(cx * cx + cy * cy + cz * cz)
    theta = np.arctan2(cn, ax_ * bx + ay_ * by + az_ * bz)
    noise = sigma_h * _DOG_NOISE / (s * sigma_px**2) if np.isfinite(sigma_h) else 0.0
    # The bias belongs to the photometric set-up (lights, material), not to a pixel: the
    # correction is made everywhere or nowhere.
    if fast_median(theta[support][::4]) <= significance * np.hypot(bias_floor_rad, noise):
        return out
    theta = theta * np.clip(w / np.float32(min_support), 0, 1)
    apply = m & np.isfinite(nx) & (theta > 0) & (cn > 0)
    if not apply.any():
        return out
    # Rodrigues: R·v = v cos θ + (a × v) sin θ + a (a·v)(1 − cos θ), a = c/|c|.
    t = theta[apply][:, None]
    ax = np.stack([cx[apply], cy[apply], cz[apply]], axis=-1) / cn[apply][:, None]
    v = n[apply]
    cos_t, sin_t = np.cos(t), np.sin(t)
    out[apply] = (
        v * cos_t
        + np.cross(ax, v) * sin_t
        + ax * np.sum(ax * v, axis=-1, keepdims=True) * (1 - cos_t)
    )
    return out


def _weights(support, sig):
    """Smoothing weights (1/σ² relative to the typical one, ≤ 1) and the typical σ."""
    if sig is None:
        return support.astype(np.float32), float("nan")
    ok = support & np.isfinite(sig) & (sig > 0)
    if not ok.any():
        return support.astype(np.float32), float("nan")
    typical = float(fast_median(sig[ok][::4]))  # a quarter of the pixels fix it to ~1 %
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(ok, np.square(typical / sig), 0)
    return np.minimum(rel, 1).astype(np.float32), typical
