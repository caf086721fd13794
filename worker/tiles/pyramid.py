"""Image pyramids by 2×2 box averaging (pure functions on arrays, no I/O).

Level l + 1 → l halves each side (odd sides: the last row/column stands alone, so texel i of
a level with pixel step s covers full-resolution pixels [i·s, (i+1)·s) exactly, as the IIIF
tiles and the quadtree assume). Heights are averaged over their valid pixels only: a texel is
valid when at least half of its full-resolution pixels are (the mean of the mask ≥ 0.5),
so the coarse silhouette follows the fine one instead of growing by a texel per level.
"""

from __future__ import annotations

import numpy as np

__all__ = ["HeightLevel", "halve_height", "halve_image", "height_level0"]


def halve_image(image: np.ndarray) -> np.ndarray:
    """(H, W[, C]) → (⌈H/2⌉, ⌈W/2⌉[, C]): the mean of each 2×2 block (fewer at odd edges),
    rounded to the input's dtype."""
    img = np.asarray(image)
    h, w = img.shape[:2]
    acc = np.zeros(((h + 1) // 2, (w + 1) // 2, *img.shape[2:]), np.float32)
    cnt = np.zeros(((h + 1) // 2, (w + 1) // 2), np.float32)
    for dy in (0, 1):
        for dx in (0, 1):
            part = img[dy::2, dx::2]
            acc[: part.shape[0], : part.shape[1]] += part
            cnt[: part.shape[0], : part.shape[1]] += 1.0
    mean = acc / (cnt if img.ndim == 2 else cnt[..., None])
    if np.issubdtype(img.dtype, np.integer):
        info = np.iinfo(img.dtype)
        return np.clip(np.rint(mean), info.min, info.max).astype(img.dtype)
    return mean.astype(img.dtype)


class HeightLevel:
    """A level of the height pyramid: the weighted sum and the weight (valid fraction) of
    each texel, both means over the texel's full-resolution pixels."""

    def __init__(self, weighted_um: np.ndarray, weight: np.ndarray):
        self.weighted_um = weighted_um
        self.weight = weight

    def height_um(self) -> np.ndarray:
        """(h, w) float32 heights in µm, NaN where fewer than half the pixels are valid."""
        with np.errstate(invalid="ignore", divide="ignore"):
            h = self.weighted_um / self.weight
        return np.where(self.weight >= 0.5, h, np.nan).astype(np.float32)


def height_level0(height_um: np.ndarray) -> HeightLevel:
    """The full-resolution level of a height map (NaN = no data)."""
    h = np.asarray(height_um, np.float32)
    ok = np.isfinite(h)
    return HeightLevel(np.where(ok, h, 0.0).astype(np.float32), ok.astype(np.float32))


def halve_height(level: HeightLevel) -> HeightLevel:
    """The next coarser level: 2×2 means of the weighted heights and of the weights; edge
    texels of odd sides average the pixels they have, counting the missing ones as invalid."""

    def half_sum(a: np.ndarray) -> np.ndarray:
        h, w = a.shape
        out = np.zeros(((h + 1) // 2, (w + 1) // 2), np.float32)
        for dy in (0, 1):
            for dx in (0, 1):
                part = a[dy::2, dx::2]
                out[: part.shape[0], : part.shape[1]] += part
        return out * np.float32(0.25)

    return HeightLevel(half_sum(level.weighted_um), half_sum(level.weight))
