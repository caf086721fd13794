"""How far to trust each height of a model: source classes and a per-pixel uncertainty (µm).

Pure functions on the model's quality maps (``quality/*.npy``, docs/reconstruction.md §7):

- ``fringe_disagreement_um`` = fringe height − final height, NaN where no fringe height exists
  (shadowed for every azimuth): there the height rests on the normals alone;
- ``guard`` (uint8): 1 where the guard replaced a height breaking the fringe bound, 2 where it
  replaced its neighbourhood (the replaced heights are harmonic fills);
- ``photometric_residual`` and ``lights_used``: the normals' angular noise
  (``worker.recon.quality.normal_sigma_rad``);
- ``walls`` (uint8, optional): pixels a refinement (the cliff refinement) changed.

Source classes (``TRUST_CLASSES``): each tablet pixel gets the first that applies of
filled (guard ≠ 0), refined (walls ≠ 0), normals only (no fringe height), disagree
(|fringe − final| > ``DISAGREE_K`` × the local RMS noise floor, i.e. the fringe and the
normals pulled the surface apart by more than the fringes' own noise explains), agree.

Height uncertainty σ_h (µm), a conservative per-pixel estimate:

- where a fringe height exists, the local RMS of the disagreement d = f − h (normalised
  Gaussian convolution of d² over the fringe pixels, σ = ``RMS_SIGMA_PX``): the fused height
  lies between the fringes and the normals, so |f − h| bounds its error by the fringes' own
  noise plus any bias between the two (an over-estimate where the fusion averaged the fringe
  noise away, which is the safe side);
- elsewhere (normals only, filled, and pixels whose fringe the guard distrusted) the height
  was carried in by integrating slopes from the nearest anchored pixel: a random walk of n
  independent slope steps of error s·σ_θ (s the pixel size, σ_θ the normals' angular noise)
  has standard deviation s·σ_θ·√n (Agrawal, Raskar & Chellappa 2006, "What is the range of
  surface reconstructions from a gradient field?": the integration error of a noisy gradient
  field grows with the path length; √n for independent steps), added in quadrature to the
  anchor's σ_h. n is the Euclidean distance to the nearest anchored pixel
  (``scipy.ndimage.distance_transform_edt``). A model without any fringe height (photometric
  stereo alone: the surface's absolute height is undefined) is anchored at its innermost
  pixel (largest distance to the mask's rim), so σ_h says how far heights can drift relative
  to the middle of the tablet.

A difference of two heights a and b then has σ ≤ σ_a + σ_b (fully correlated errors, the
worst case; √(σ_a² + σ_b²) if independent): the viewer reports the former.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from worker.recon.quality import NORMAL_FLOOR_RAD, normal_sigma_rad

__all__ = [
    "DISAGREE_K",
    "RMS_SIGMA_PX",
    "TRUST_CLASSES",
    "encode_trust_rgba",
    "height_uncertainty_um",
    "trust_classes",
]

# Class codes of trust.png's red channel (0 = off the tablet).
TRUST_CLASSES = {
    1: "agree: fringes and normals agree",
    2: "disagree: fringes and normals disagree beyond the fringe noise",
    3: "normals only: no fringe height, integrated from slopes",
    4: "filled: the guard replaced the height (harmonic fill)",
    5: "refined: a refinement (cliff walls) changed the height",
}
AGREE, DISAGREE, NORMALS_ONLY, FILLED, REFINED = 1, 2, 3, 4, 5
# |d| beyond this many times the image's robust noise level of d is a disagreement: 3σ keeps
# 99.7 % of Gaussian noise out.
DISAGREE_K = 3.0
# The local RMS of the disagreement: over a few pixels, so one wedge's rim does not spread
# over its neighbours, but more than one, so a single noisy fringe pixel is averaged.
RMS_SIGMA_PX = 2.0
# The normals' noise along an integration path: averaged over this many pixels (a path is
# tens of pixels long; one pixel's residual is itself noisy).
PATH_SIGMA_PX = 8.0


def _robust_sigma(values: np.ndarray) -> float:
    """1.4826 × median absolute deviation: σ of Gaussian noise, blind to a few outliers."""
    if values.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def trust_classes(
    mask: np.ndarray,
    disagreement_um: np.ndarray | None,
    guard: np.ndarray | None = None,
    walls: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) uint8 source class per pixel (``TRUST_CLASSES``; 0 off the mask).

    disagreement_um: fringe − final height, NaN where there is no fringe height; None when
    the model has no fringe heights at all (every pixel rests on the normals)."""
    mask = np.asarray(mask, bool)
    out = np.zeros(mask.shape, np.uint8)
    if disagreement_um is None:
        out[mask] = NORMALS_ONLY
    else:
        d = np.asarray(disagreement_um, np.float64)
        if d.shape != mask.shape:
            raise ValueError(f"disagreement {d.shape} and mask {mask.shape} must match")
        has = mask & np.isfinite(d)
        noise = _robust_sigma(d[has])
        out[mask] = NORMALS_ONLY
        out[has] = AGREE
        out[has & (np.abs(d) > DISAGREE_K * noise)] = DISAGREE
    for flags, code in ((walls, REFINED), (guard, FILLED)):
        if flags is not None:
            f = np.asarray(flags)
            if f.shape != mask.shape:
                raise ValueError(f"flag map {f.shape} and mask {mask.shape} must match")
            out[mask & (f != 0)] = code
    return out


def height_uncertainty_um(
    mask: np.ndarray,
    disagreement_um: np.ndarray | None,
    *,
    pixel_size_um: float,
    normal_sigma: np.ndarray | float = NORMAL_FLOOR_RAD,
    guard: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) float32 σ_h in µm on the mask, NaN off it (module docstring for the model).

    normal_sigma: the normals' angular noise in rad, per pixel or one value (inf/NaN where
    no normal was solved: the floor is used)."""
    mask = np.asarray(mask, bool)
    if not pixel_size_um > 0:
        raise ValueError(f"pixel_size_um must be > 0, got {pixel_size_um}")
    sig_t = np.broadcast_to(np.asarray(normal_sigma, np.float64), mask.shape)
    sig_t = np.where(np.isfinite(sig_t), sig_t, NORMAL_FLOOR_RAD)
    if disagreement_um is None:
        anchored = np.zeros(mask.shape, bool)
        d2 = np.zeros(mask.shape)
    else:
        d = np.asarray(disagreement_um, np.float64)
        if d.shape != mask.shape:
            raise ValueError(f"disagreement {d.shape} and mask {mask.shape} must match")
        anchored = mask & np.isfinite(d)
        d2 = np.where(anchored, d, 0.0) ** 2
    if guard is not None:
        anchored &= np.asarray(guard) == 0
    out = np.full(mask.shape, np.nan, np.float32)
    if not mask.any():
        return out
    if anchored.any():
        w = ndimage.gaussian_filter(anchored.astype(np.float64), RMS_SIGMA_PX)
        num = ndimage.gaussian_filter(np.where(anchored, d2, 0.0), RMS_SIGMA_PX)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(np.where(anchored, num / np.maximum(w, 1e-12), 0.0))
        dist, (ri, ci) = ndimage.distance_transform_edt(~anchored, return_indices=True)
        anchor_sigma = rms[ri, ci]
    else:
        # No fringe height: anchored at the innermost pixel of the mask.
        inner = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
        seed = np.unravel_index(int(np.argmax(inner)), mask.shape)
        free = np.ones(mask.shape, bool)
        free[seed] = False
        dist = ndimage.distance_transform_edt(free)
        anchor_sigma = np.zeros(mask.shape)
    # The walk's variance is the sum of its steps' σ_θ² along the path: the local mean of σ_θ²
    # (over the tablet, PATH_SIGMA_PX) stands for it, not one pixel's noisy value.
    on = mask.astype(np.float64)
    var_t = ndimage.gaussian_filter(np.where(mask, sig_t**2, 0.0), PATH_SIGMA_PX)
    sig_path = np.sqrt(var_t / np.maximum(ndimage.gaussian_filter(on, PATH_SIGMA_PX), 1e-12))
    walk = pixel_size_um * np.tan(np.minimum(sig_path, 1.0)) * np.sqrt(dist)
    sigma = np.sqrt(anchor_sigma**2 + walk**2)
    out[mask] = sigma[mask]
    return out


def normal_sigma_from_maps(
    residual: np.ndarray | None, lights_used: np.ndarray | None, *, polar_deg: float = 45.0
) -> np.ndarray | float:
    """σ_θ per pixel from the photometric maps, or the floor when the model lacks them."""
    if residual is None or lights_used is None:
        return NORMAL_FLOOR_RAD
    return normal_sigma_rad(
        np.nan_to_num(np.asarray(residual, np.float32), nan=np.inf),
        np.asarray(lights_used),
        polar_deg=polar_deg,
    )


def encode_trust_rgba(
    classes: np.ndarray,
    disagreement_um: np.ndarray | None,
    sigma_um: np.ndarray,
    *,
    disagreement_scale_um: float,
    sigma_scale_um: float,
) -> np.ndarray:
    """(H, W, 4) uint8 trust.png: R = class code, G = round(255·min(1, |d|/scale_d)) (0 where
    no fringe height), B = round(255·min(1, σ_h/scale_σ)), A = 255 on the tablet."""
    if not (disagreement_scale_um > 0 and sigma_scale_um > 0):
        raise ValueError("the legend scales must be > 0 µm")
    mask = classes > 0

    def unit8(v: np.ndarray, scale: float) -> np.ndarray:
        t = np.clip(np.nan_to_num(np.abs(v), nan=0.0) / scale, 0.0, 1.0)
        return np.where(mask, np.rint(255.0 * t), 0).astype(np.uint8)

    d = np.zeros(classes.shape) if disagreement_um is None else disagreement_um
    return np.stack(
        [
            classes.astype(np.uint8),
            unit8(d, disagreement_scale_um),
            unit8(sigma_um, sigma_scale_um),
            np.where(mask, 255, 0).astype(np.uint8),
        ],
        axis=-1,
    )


def legend_scale_um(values: np.ndarray, mask: np.ndarray) -> float:
    """The top of a legend in µm: the 98th percentile of |values| on the mask, rounded up to
    1, 2 or 5 × 10^k (so the legend reads 0 … 20 µm, not 0 … 17.3 µm), at least 1 µm."""
    v = np.abs(values[np.asarray(mask, bool) & np.isfinite(values)])
    top = float(np.percentile(v, 98)) if v.size else 1.0
    top = max(top, 1.0)
    exp = 10 ** np.floor(np.log10(top))
    for f in (1, 2, 5, 10):
        if f * exp >= top:
            return float(f * exp)
    return float(10 * exp)
