"""Noise levels of the measurements, estimated from the data (inputs to the fusion weights).

- Normals: photometric stereo with K inlier lights at polar angle θ fits b = ρn by least
  squares; with shading noise σ_s (in units of n·l) the tangential error of n has variance
  ≈ σ_s²·2/(K·sin²θ) per component (LᵀL ≈ diag(K sin²θ/2, K sin²θ/2, K cos²θ)). σ_s is the
  RMS residual corrected for the 3 fitted parameters, √(K/(K−3))·residual; pixels with
  K = 3 (no residual) take the image's median. A floor of `floor_rad` stands for what the
  residual cannot see (calibration of the light directions, non-Lambertian bias).
- Fringe heights: σ_f from the data itself, 1.4826·MAD/√6 of the second differences
  h[i+1] − 2h[i] + h[i−1] along rows and columns (they cancel the surface's slope; white
  noise gives them variance 6σ²), per pixel divided by √(azimuths used / median used).
"""

from __future__ import annotations

import cv2
import numpy as np

from worker.recon.arrays import fast_median

__all__ = [
    "tilt_bias_rad",
    "NORMAL_FLOOR_RAD",
    "crease_sigma_um",
    "fringe_blur_px",
    "fringe_sigma_um",
    "normal_sigma_rad",
]

# What a photometric normal's residual cannot show (light calibration, non-Lambertian bias):
# the floor of its predicted angular noise.
NORMAL_FLOOR_RAD = 0.003


def normal_sigma_rad(
    residual: np.ndarray,
    lights_used: np.ndarray,
    *,
    polar_deg: float,
    floor_rad: float = NORMAL_FLOOR_RAD,
) -> np.ndarray:
    """(H, W) float32 angular noise of photometric normals (rad); inf where not solved.

    residual: (H, W) RMS misfit in units of n·l; lights_used: (H, W) inlier count.
    """
    res = np.asarray(residual, np.float32)
    k = np.asarray(lights_used, np.float32)
    if res.shape != k.shape:
        raise ValueError(f"residual {res.shape} and lights_used {k.shape} must match")
    if not 0 < polar_deg < 90:
        raise ValueError(f"polar_deg must be in (0, 90), got {polar_deg}")
    solved = np.isfinite(res) & (k >= 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma_s = np.where(k > 3, res * np.sqrt(k / np.maximum(k - 3, 1)), np.nan)
    fit = solved & np.isfinite(sigma_s) & (k > 3)
    typical = float(fast_median(sigma_s[fit])) if fit.any() else 0.02
    sigma_s = np.where(fit, sigma_s, typical)
    sin2 = np.sin(np.radians(polar_deg)) ** 2
    sig = sigma_s * np.sqrt(2.0 / (np.maximum(k, 3) * sin2))
    sig = np.sqrt(sig**2 + floor_rad**2)
    return np.where(solved, sig, np.inf).astype(np.float32, copy=False)


def fringe_sigma_um(
    height_um: np.ndarray,
    mask: np.ndarray,
    *,
    azimuths_used: np.ndarray | None = None,
    floor_um: float = 0.05,
) -> tuple[np.ndarray, float]:
    """Per-pixel noise of the fringe heights (µm) and the image-wide estimate σ_f.

    height_um: (H, W) NaN where none; mask: (H, W) bool. Returns ((H, W) float32, inf where
    no height; σ_f).
    """
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool) & np.isfinite(h)
    if h.shape != m.shape:
        raise ValueError(f"height_um {h.shape} and mask {m.shape} must match")
    out = np.full(h.shape, np.inf, np.float32)
    if m.sum() < 25:
        return out, float("inf")
    # Second differences cancel the surface's slope; white noise gives them variance 6σ²;
    # the MAD ignores the few large values at creases and wedge rims.
    d2 = [
        (h[:, 2:] - 2 * h[:, 1:-1] + h[:, :-2])[m[:, 2:] & m[:, 1:-1] & m[:, :-2]],
        (h[2:, :] - 2 * h[1:-1, :] + h[:-2, :])[m[2:, :] & m[1:-1, :] & m[:-2, :]],
    ]
    sample = np.concatenate(d2)
    if sample.size < 25:
        return out, float("inf")
    mad = float(fast_median(np.abs(sample - fast_median(sample))))
    sigma = max(1.4826 * mad / np.sqrt(6.0), floor_um)
    if azimuths_used is not None:
        a = np.asarray(azimuths_used, np.float32)
        typical = float(fast_median(a[m])) if m.any() else 1.0
        scale = np.sqrt(typical / np.maximum(a, 1))
    else:
        scale = np.ones(h.shape, np.float32)
    out[m] = (sigma * scale)[m]
    return out, sigma


def crease_sigma_um(
    normals: np.ndarray, *, pixel_size_um: float, blur_px: float = 0.0
) -> np.ndarray:
    """(H, W) float32 model error of a fringe height where the surface bends within a pixel.

    A fringe pixel reports (about) the height averaged over its area, not the height at its
    centre; the two differ by ≈ s²·∇²h/24 on a smooth surface and by up to s·Δg/8 at a crease
    (slope jump Δg across the pixel). With ∇²h estimated from the normals' slopes by central
    differences (a crease shows as Δg/(2s) there), s²·|∇²h|/8 bounds that error; it is added in
    quadrature to the fringe noise so that wedge rims and bottoms take their shape from the
    normals. NaN normals count as flat.

    blur_px: σ (px) by which the fringe heights are smoothed relative to the normals
    (`fringe_blur_px`: light inside the clay, a defocused projector); a Gaussian of σ moves
    a height by (σ²/2)·∇²h (the heat equation's first step), added to the bound:
    s²·|∇²h|·(1/8 + σ²/2).
    """
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    n = np.asarray(normals, np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must have shape (H, W, 3), got {n.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        gx = np.nan_to_num(n[..., 0] / n[..., 2], nan=0.0, posinf=0.0, neginf=0.0)
        gy = np.nan_to_num(n[..., 1] / n[..., 2], nan=0.0, posinf=0.0, neginf=0.0)
    s = float(pixel_size_um)
    laplacian = (np.gradient(gx, axis=1) + np.gradient(gy, axis=0)) / s
    gain = 1.0 / 8.0 + 0.5 * float(blur_px) ** 2
    return (s * s * np.abs(laplacian) * gain).astype(np.float32, copy=False)


FRINGE_BLUR_CANDIDATES_PX = (0.0, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)


def fringe_blur_px(
    fringe_height_um: np.ndarray,
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    pixel_size_um: float,
    candidates_px: tuple[float, ...] = FRINGE_BLUR_CANDIDATES_PX,
    crease_share: float = 0.1,
) -> float:
    """σ (px) of the Gaussian by which the fringe heights are smoother than the normals.

    Light scattered inside the clay and a defocused projector blur the fringe pattern on the
    object, hence its phase, hence the heights, while the photometric normals keep the
    surface's fine detail (the camera's blur acts on both alike and cancels here). So the
    fringe heights' slopes (central differences, ∇f) are compared with the normals' slopes
    g smoothed by the same central difference ([¼ ½ ¼]) and by a Gaussian of each candidate
    σ: the σ whose smoothed slopes fit ∇f best (median |∇f − G_σ*g| over the creases, the
    `crease_share` of the pixels where g bends most, where a blur shows and the normals'
    noise counts least; a median, so that cliffs and unwrapping errors do not vote) is the
    fringes' blur relative to the normals. It feeds `crease_sigma_um`, so that where the
    fringes are blurred the fusion takes the wedges' shape from the normals (issue 15).
    Returns 0 when nothing can be compared.

    fringe_height_um: (H, W) µm, NaN where none; normals: (H, W, 3); mask: (H, W) bool.
    """
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    f = np.asarray(fringe_height_um, np.float32)
    n = np.asarray(normals, np.float32)
    m = np.asarray(mask, bool)
    if not m.any():
        return 0.0
    rows = np.flatnonzero(m.any(axis=1))
    cols = np.flatnonzero(m.any(axis=0))
    pad = int(np.ceil(3 * max(candidates_px))) + 2
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, m.shape[0])
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, m.shape[1])
    f, n, m = f[r0:r1, c0:c1], n[r0:r1, c0:c1], m[r0:r1, c0:c1]
    s = float(pixel_size_um)
    with np.errstate(invalid="ignore", divide="ignore"):
        gx = n[..., 0] / n[..., 2]
        gy = n[..., 1] / n[..., 2]
    steep = float(np.tan(np.radians(60.0)))
    ok_g = m & np.isfinite(gx) & np.isfinite(gy) & (np.abs(gx) < steep) & (np.abs(gy) < steep)
    gx, gy = np.where(ok_g, gx, 0).astype(np.float32), np.where(ok_g, gy, 0).astype(np.float32)
    w = ok_g.astype(np.float32)
    fx = np.full(f.shape, np.nan, np.float32)
    fy = np.full(f.shape, np.nan, np.float32)
    fx[:, 1:-1] = (f[:, 2:] - f[:, :-2]) / np.float32(2 * s)
    fy[1:-1, :] = (f[2:, :] - f[:-2, :]) / np.float32(2 * s)
    tri = np.array([[0.25, 0.5, 0.25]], np.float32)
    # The central difference of h is the mean slope over two pixels: [¼ ½ ¼] along its axis.
    sx = cv2.filter2D(gx * w, -1, tri, borderType=cv2.BORDER_CONSTANT)
    sy = cv2.filter2D(gy * w, -1, tri.T, borderType=cv2.BORDER_CONSTANT)
    wx = cv2.filter2D(w, -1, tri, borderType=cv2.BORDER_CONSTANT)
    wy = cv2.filter2D(w, -1, tri.T, borderType=cv2.BORDER_CONSTANT)
    full = cv2.erode(ok_g.astype(np.uint8), np.ones((2 * pad - 1, 2 * pad - 1), np.uint8)) > 0
    use = full & np.isfinite(fx) & np.isfinite(fy)
    bend = np.abs(np.gradient(gx, axis=1)) + np.abs(np.gradient(gy, axis=0))
    if use.sum() < 100:
        return 0.0
    cut = np.quantile(bend[use], 1.0 - crease_share)
    use &= bend >= cut
    if use.sum() < 50:
        return 0.0
    scores = []
    for sigma in candidates_px:
        if sigma > 0:
            k = 2 * int(np.ceil(3 * sigma)) + 1
            bx = cv2.GaussianBlur(sx, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
            by = cv2.GaussianBlur(sy, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
            nx = cv2.GaussianBlur(wx, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
            ny = cv2.GaussianBlur(wy, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
        else:
            bx, by, nx, ny = sx, sy, wx, wy
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.abs(fx[use] - bx[use] / nx[use]) + np.abs(fy[use] - by[use] / ny[use])
        scores.append(float(np.median(r)))
    return float(candidates_px[int(np.argmin(scores))])


def tilt_bias_rad(
    normals: np.ndarray,
    height_um: np.ndarray,
    mask: np.ndarray,
    *,
    pixel_size_um: float,
    edges_deg: tuple[float, ...] = (0.0, 30.0, 45.0, 55.0, 65.0, 75.0, 90.0),
    min_pixels: int = 200,
    from_deg: float = 45.0,
) -> np.ndarray:
    """(H, W) float32 rad: the normals' systematic tilt error, measured on this scan, by
    how steep they are; 0 where it is within the noise.

    Photometric normals on steep ground come out too steep or too flat (attached shadows
    leave few lights on one side, interreflection and light inside the clay fill them in),
    and their residual does not show it: on a Mitsuba scan the tablet's rim (true slope
    ~67°) was 4.5° too steep where `normal_sigma_rad` claimed 0.85°. The fringe heights,
    unbiased in the mean, measure it: per class of measured tilt θ_n (`edges_deg`), the
    median of θ_n − θ_f, θ_f the tilt of the heights' central-difference gradient, over
    pixels of the mask whose four neighbours are on it too. A class with fewer than
    `min_pixels`, or whose median is within 3 standard errors of zero (1.4826·MAD/√N·1.25),
    gets 0, and so do the classes below `from_deg`: on gentler ground a tilt bias is a
    smooth rotation that `normal_bias.correct_normal_bias` takes out (counted there too,
    it cost hard noise 512×384 its normal median, 0.45° → 0.57°). Added in quadrature to
    the normals' σ, it lets the fringe heights hold steep ground where the normals are
    biased (issue 15 item 4: weights from the data).
    """
    n = np.asarray(normals, np.float32)
    h = np.asarray(height_um, np.float32)
    m = np.asarray(mask, bool)
    out = np.zeros(h.shape, np.float32)
    if not pixel_size_um > 0:
        raise ValueError("pixel_size_um must be > 0")
    nz = -n[..., 2]
    with np.errstate(invalid="ignore"):
        tilt_n = np.degrees(np.arccos(np.clip(nz, -1.0, 1.0)))
    gx = np.full(h.shape, np.nan, np.float32)
    gy = np.full(h.shape, np.nan, np.float32)
    gx[:, 1:-1] = (h[:, 2:] - h[:, :-2]) / np.float32(2 * pixel_size_um)
    gy[1:-1, :] = (h[2:, :] - h[:-2, :]) / np.float32(2 * pixel_size_um)
    inner = cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
    tilt_f = np.degrees(np.arctan(np.hypot(gx, gy)))
    ok = inner & np.isfinite(tilt_n) & np.isfinite(tilt_f)
    if not ok.any():
        return out
    cls = np.digitize(tilt_n, edges_deg[1:-1])
    d = np.radians(tilt_n - tilt_f)
    for k in range(len(edges_deg) - 1):
        if edges_deg[k] < from_deg:
            continue
        sel = ok & (cls == k)
        count = int(np.count_nonzero(sel))
        if count < min_pixels:
            continue
        v = d[sel]
        med = float(np.median(v))
        se = 1.25 * 1.4826 * float(np.median(np.abs(v - med))) / np.sqrt(count)
        if abs(med) > 3 * se:
            out[(cls == k) & m] = abs(med)
    return out
