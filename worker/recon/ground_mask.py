"""The object on a dark ground, from a stack of photographs under many lights.

A bundle of photometric frames alone (no projector, perhaps no reference target) has no
heights to tell the object from what it rests on; it has the lit images. A dark ground
(black velvet, ρ ≈ 0.01–0.03) reads near the camera's noise floor under every light, while
every part of the object faces some light: its brightest samples stand above the ground's
even where its albedo is low (a dark glaze) or most of its lights are shadowed (a crease).
So the evidence is, per pixel, a high quantile of its samples over the lights (`stack_peak`):
a dark object's highlights and a crease's few lit samples count, a single hot or noisy
sample does not.

`ground_mask(peak)`:

1. Otsu's threshold (1979) on log peak splits ground from object (the two differ by a
   factor); the ground class gives the ground's level μ (its median) and the pixel noise
   σ (1.4826·MAD of neighbour differences over √2: a smooth fall-off of the light does not
   count), both measured on this scan.
2. A pixel is object where its peak exceeds the ground's level where it lies by 6σ, and
   by a tenth of it at least (noiseless data) (the
   level: the ground pixels smoothed over a sixteenth of the image, carried under the
   object from around it, vignetting and fall-off included) and, near the
   silhouette, where it exceeds half-way from the ground's level to the object's beside it
   (its neighbours inside): a rim pixel is object when the object covers its centre, more
   than half of it (the output is a point sample, SCAN_BUNDLE.md).
3. Morphology: one opening (specks, hot pixels), the connected parts at least
   `min_part_fraction` of the largest (a figurine's ears and tail are parts too), holes
   filled (a crease dark under every light is object all the same).

It stands down to "everything measured" with a reason, rather than cut the object, when
the ground does not surround the object (the ground class holds less than half of the
image border), when the two classes are not apart (their medians within a factor 1.5), or
when nearly nothing or nearly everything would be object.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from worker.recon.mask import otsu_threshold

__all__ = ["GroundMask", "ground_mask", "stack_peak"]

_K_SIGMA = 6.0
_MIN_MARGIN = 0.1
_MIN_RATIO = 1.5
_BORDER_PX = 4


@dataclass(frozen=True)
class GroundMask:
    """The object mask (H, W) bool; the ground's level and spread and the noise-floor
    threshold (units of the peak); stood_down: the reason the mask is everything measured
    instead (None when it found the object)."""

    mask: np.ndarray
    ground_level: float
    ground_sigma: float
    threshold: float
    stood_down: str | None = None


def stack_peak(stack: np.ndarray, *, quantile: float = 0.95) -> np.ndarray:
    """Per pixel, the `quantile` of its finite samples over the first axis, (H, W) float32.

    stack: (K, H, W) radiance or shading of K lights, NaN where unusable. With K ≥ 20 one
    sample in twenty (a hot pixel, a cosmic ray) cannot raise it; with fewer lights it is
    the second-brightest sample at most (never the maximum of a handful: one outlier).
    """
    s = np.asarray(stack, np.float32)
    if s.ndim != 3 or s.shape[0] < 1:
        raise ValueError(f"stack must be (K, H, W), got {s.shape}")
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must lie in (0, 1], got {quantile}")
    k = s.shape[0]
    rank = min(int(np.floor(quantile * (k - 1))), max(k - 2, 0))
    filled = np.where(np.isfinite(s), s, -np.inf)
    out = np.partition(filled, rank, axis=0)[rank]
    return np.where(np.isfinite(out), out, np.nan).astype(np.float32)


def _everything(peak, has_normal, level, sigma, threshold, reason) -> GroundMask:
    mask = np.isfinite(peak)
    if has_normal is not None:
        mask &= has_normal
    return GroundMask(mask, level, sigma, threshold, reason)


def ground_mask(
    peak: np.ndarray,
    *,
    has_normal: np.ndarray | None = None,
    min_part_fraction: float = 0.01,
) -> GroundMask:
    """The object standing on a dark ground, from the per-pixel peak over the lights
    (`stack_peak`); has_normal (H, W) bool: where photometric stereo gave a normal (the
    stood-down mask is those pixels)."""
    v = np.asarray(peak, np.float32)
    if v.ndim != 2:
        raise ValueError(f"peak must be (H, W), got {v.shape}")
    if has_normal is not None:
        has_normal = np.asarray(has_normal, bool)
        if has_normal.shape != v.shape:
            raise ValueError(f"has_normal shape {has_normal.shape} does not match peak {v.shape}")
    finite = np.isfinite(v)
    if finite.sum() < 64:
        return _everything(v, has_normal, np.nan, np.nan, np.nan, "fewer than 64 measured pixels")
    vals = v[finite]
    # The ground may read at or below zero after dark subtraction: log of a floor.
    floor = max(float(np.percentile(vals, 99.0)) * 1e-4, 1e-12)
    logv = np.log(np.maximum(vals, floor))
    try:
        t = float(np.exp(otsu_threshold(logv)))
    except ValueError:
        return _everything(v, has_normal, np.nan, np.nan, np.nan, "the pixels all read the same")
    low_px = finite & (v <= t)
    low, high = v[low_px], v[finite & (v > t)]
    if low.size < 16 or high.size < 16:
        return _everything(v, has_normal, np.nan, np.nan, np.nan, "no two brightness classes")
    level = float(np.median(low))
    sigma = _pixel_noise(v, low_px)
    if float(np.median(high)) < _MIN_RATIO * max(level, floor):
        return _everything(
            v,
            has_normal,
            level,
            sigma,
            level + _K_SIGMA * sigma,
            f"the object is not brighter than the ground (class medians {np.median(high):.3g}"
            f" and {level:.3g}, less than {_MIN_RATIO}× apart)",
        )
    # The ground's level where it lies (vignetting, a lamp's fall-off): the pixels within
    # the noise floor of it, smoothed over a sixteenth of the image and carried under the
    # object from around it; twice more from the pixels within the floor of that.
    # At least a tenth of the ground's level: noiseless data (a renderer's) would otherwise
    # take the ground's own shading (a shadow's edge, light bounced off the object) for
    # object.
    margin = np.float32(max(_K_SIGMA * sigma, _MIN_MARGIN * level))
    threshold = level + float(margin)
    on_ground = finite & (v <= threshold)
    for _ in range(3):
        ground = _smooth_over(v, on_ground, max(v.shape) / 16.0)
        ground = np.where(np.isfinite(ground), ground, level).astype(np.float32)
        on_ground = finite & (v <= ground + margin)
    fg = finite & ~on_ground
    border = np.ones(v.shape, bool)
    border[_BORDER_PX:-_BORDER_PX, _BORDER_PX:-_BORDER_PX] = False
    ground_share = float(np.mean(~fg[border & finite])) if (border & finite).any() else 0.0
    if ground_share < 0.5:
        return _everything(
            v,
            has_normal,
            level,
            sigma,
            threshold,
            f"no dark ground around the object (only {100 * ground_share:.0f} % of the image"
            " border is ground)",
        )
    fg = _rim_half_coverage(v, fg, ground)
    fg = _parts(fg, min_part_fraction)
    share = float(fg.mean())
    if not 0.001 <= share <= 0.98:
        return _everything(
            v,
            has_normal,
            level,
            sigma,
            threshold,
            f"the object would cover {100 * share:.1f} % of the image",
        )
    return GroundMask(fg, level, sigma, threshold, None)


def _pixel_noise(v: np.ndarray, where: np.ndarray) -> float:
    """σ of the pixel-to-pixel noise of v over `where`: 1.4826·MAD of the differences of
    horizontal and vertical neighbours, over √2 (a smooth variation of the level, a
    lamp's fall-off, does not count)."""
    dx = (v[:, 1:] - v[:, :-1])[where[:, 1:] & where[:, :-1]]
    dy = (v[1:, :] - v[:-1, :])[where[1:, :] & where[:-1, :]]
    d = np.concatenate([dx, dy])
    if d.size < 16:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def _smooth_over(v: np.ndarray, where: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian mean of v over the pixels `where` (normalised convolution, Knutsson &
    Westin 1993); NaN far from any of them."""
    w = where.astype(np.float32)
    num = cv2.GaussianBlur(np.where(where, v, 0).astype(np.float32), (0, 0), sigma_px)
    den = cv2.GaussianBlur(w, (0, 0), sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-3, num / den, np.nan)


def _rim_half_coverage(v: np.ndarray, fg: np.ndarray, level: np.ndarray) -> np.ndarray:
    """fg without the rim pixels (its outer ring) that read less than half-way from the
    ground's level to the object's beside them (the mean of their 8-neighbours inside the
    ring). Further inside the object's own shading varies (a limb darkens): on the rendered
    dark glossy ball, comparing with the object 3 px inside cut a third of the rim pixels
    whose centre is on the ball (IoU 0.951, against 0.980 with the neighbours)."""
    square = np.ones((3, 3), np.uint8)
    inner = cv2.erode(
        fg.astype(np.uint8), square, iterations=1, borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    rim = fg & (inner == 0)
    w = (3, 3)
    vin = np.where(inner > 0, np.nan_to_num(v), 0).astype(np.float32)
    total = cv2.boxFilter(vin, -1, w, normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(
        inner.astype(np.float32), -1, w, normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        beside = total / count
    # Thin parts have no inside to compare with: kept as the noise floor found them.
    judged = rim & (count > 0)
    drop = judged & (v < 0.5 * (level + beside))
    return fg & ~drop


def _parts(fg: np.ndarray, min_part_fraction: float) -> np.ndarray:
    """One opening, the parts at least `min_part_fraction` of the largest, holes filled."""
    square = np.ones((3, 3), np.uint8)
    fg = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_OPEN, square).astype(bool)
    labels, count = ndimage.label(fg)
    if count == 0:
        return fg
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    keep = np.concatenate([[False], sizes >= max(min_part_fraction * sizes.max(), 4)])
    return ndimage.binary_fill_holes(keep[labels])
