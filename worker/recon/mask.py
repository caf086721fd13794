"""The tablet mask: which pixels show the tablet and carry a reliable measurement.

Behind the tablet lies a dark, low-albedo support (black velvet, a V-block); clay reflects
10–60 %. The mask is built from evidence that every kind of bundle has:

1. brightness: albedo (photometric or colour) or, for fringe-only bundles, the fringe
   amplitude; split by Otsu's threshold on log brightness (the two populations, support and
   clay, differ by a factor, not an offset), never below `min_albedo`; when the heights
   show a support apart from the tablet (two height classes far apart, the lower one on
   the image border: a light V-block or cloth as bright as the clay) and the brightness
   class overlaps the class above it by less than half (IoU), the class above it is the
   tablet instead;
2. reliability: pixels with neither a normal nor a fringe height are dropped; pixels whose
   fringe modulation is far below the tablet's typical value are dropped where they also
   have no normal;
3. height (optional): the support lies below the tablet; pixels much lower than the
   tablet's low percentile are dropped (a V-block or a table seen around the tablet);
4. morphology: opening (removes specks and thin bridges to the support), the largest
   connected component plus any component at least `min_part_fraction` of it, holes
   filled (wedge floors in cast shadow are tablet too), and one pixel eroded off the rim
   where pixels mix tablet and support.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

__all__ = ["otsu_threshold", "tablet_mask"]


def otsu_threshold(values: np.ndarray, *, bins: int = 256) -> float:
    """Otsu's threshold (1979) of a 1-D sample: maximises the between-class variance."""
    v = np.asarray(values, np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size < 2 or np.ptp(v) == 0:
        raise ValueError("values must hold at least two distinct finite numbers")
    hist, edges = np.histogram(v, bins=bins)
    centres = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centres)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mu0 - mu1) ** 2
    return float(edges[1:][np.argmax(between[:-1])])


def tablet_mask(
    brightness: np.ndarray,
    *,
    has_normal: np.ndarray | None = None,
    has_height: np.ndarray | None = None,
    modulation: np.ndarray | None = None,
    height_um: np.ndarray | None = None,
    min_albedo: float = 0.06,
    min_part_fraction: float = 0.2,
    opening_px: int = 2,
) -> np.ndarray:
    """Boolean (H, W) mask of the tablet.

    brightness: (H, W) albedo relative to white (or any brightness proportional to it), NaN
    where unknown. has_normal, has_height: (H, W) bool, where a normal / fringe height exists.
    modulation: (H, W) fringe modulation B/A (NaN allowed). height_um: (H, W) µm (NaN allowed).
    """
    b = np.asarray(brightness, np.float32)
    if b.ndim != 2:
        raise ValueError(f"brightness must be (H, W), got {b.shape}")
    shape = b.shape
    for name, arr in (
        ("has_normal", has_normal),
        ("has_height", has_height),
        ("modulation", modulation),
        ("height_um", height_um),
    ):
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} shape {np.shape(arr)} does not match brightness {shape}")
    finite = np.isfinite(b) & (b > 0)
    if finite.sum() < 16:
        return np.zeros(shape, bool)
    logb = np.log(b[finite])
    try:
        t = float(np.exp(otsu_threshold(logb)))
    except ValueError:
        t = 0.0
    fg = finite & (b > max(t, min_albedo))

    measured = np.zeros(shape, bool)
    if has_normal is not None:
        measured |= np.asarray(has_normal, bool)
    if has_height is not None:
        measured |= np.asarray(has_height, bool)
    if has_normal is None and has_height is None:
        measured[:] = True
    # Gaps of a few pixels in the measurements (cast shadows in wedges, unwrapping rejects)
    # are tablet all the same: the fusion bridges them; only unmeasured margins are dropped.
    measured = _fill_holes(_erode(_dilate(measured, 2), 2))
    fg &= measured
    if height_um is not None:
        raised = _raised_above_support(height_um, finite & measured)
        if raised is not None and (raised & fg).sum() < 0.5 * (raised | fg).sum():
            # A support as bright as the clay (a light V-block or cloth) that stands apart
            # in height, where brightness picked mostly the support: the tablet is what
            # stands above it. Where the two agree (IoU ≥ ½) brightness keeps its finer
            # rim (the tablet's sloping sides fall below the heights' threshold).
            fg = raised & finite & (b > 0.5 * min_albedo)
    if modulation is not None and fg.any():
        m = np.asarray(modulation, np.float32)
        tablet_m = m[fg & ~np.isnan(m)]  # np.nanmedian's values, without a whole-frame copy
        typical = np.median(tablet_m) if tablet_m.size else np.float32(np.nan)
        if np.isfinite(typical):
            weak = ~(m > 0.2 * typical)
            if has_normal is not None:
                weak &= ~np.asarray(has_normal, bool)
            fg &= ~weak
    if height_um is not None and fg.any():
        h = np.asarray(height_um, np.float32)
        hv = h[fg & np.isfinite(h)]
        if hv.size:
            lo, hi = np.percentile(hv, [2, 98])
            # The support lies well below the tablet: anything lower than the tablet's 2nd
            # percentile by more than the tablet's own height range is not tablet.
            fg &= ~(np.isfinite(h) & (h < lo - max(hi - lo, 1.0)))

    if opening_px > 0:
        fg = _dilate(_erode(fg, opening_px), opening_px)
    labels, count = ndimage.label(fg)
    if count == 0:
        return fg
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]  # pixels per part
    keep = np.concatenate([[False], sizes >= min_part_fraction * sizes.max()])
    fg = keep[labels]
    fg = _fill_holes(fg)
    return _erode(fg, 1)


def _raised_above_support(height_um, where, *, border_share: float = 0.5):
    """The pixels standing above a support that surrounds them, or None when the heights
    do not show one.

    Otsu's threshold on the heights of `where` splits them in two; the split is a support
    when the lower class holds at least `border_share` of the measured border pixels (a
    support surrounds the tablet; a chip's lower terrace lies inside it) and the higher
    class does not, and the two classes stand apart: the gap between their medians exceeds
    6 times the sum of their robust spreads (1.4826·MAD), which a tablet's own relief and
    curvature, continuous, do not.
    """
    h = np.asarray(height_um, np.float32)
    ok = where & np.isfinite(h)
    if ok.sum() < 64:
        return None
    v = h[ok]
    try:
        t = otsu_threshold(v)
    except ValueError:
        return None
    lo, hi = v[v <= t], v[v > t]
    if lo.size < 16 or hi.size < 16:
        return None

    def spread(x):
        return 1.4826 * float(np.median(np.abs(x - np.median(x))))

    if np.median(hi) - np.median(lo) <= 6 * (spread(lo) + spread(hi)):
        return None
    # A band 4 px wide: the measured region may stop a pixel or two short of the edge.
    border = np.ones(h.shape, bool)
    border[4:-4, 4:-4] = False
    edge = border & ok
    if edge.sum() < 16:
        return None
    low_share = float(np.mean(h[edge] <= t))
    if low_share < border_share:
        return None
    return ok & (h > t)


# Binary morphology with a 3×3 square as scipy.ndimage's (outside the image counts as
# background for both operations), by OpenCV on uint8, several times faster.
_SQUARE = np.ones((3, 3), np.uint8)


def _dilate(a, iterations):
    return cv2.dilate(a.astype(np.uint8), _SQUARE, iterations=iterations).astype(bool)


def _erode(a, iterations):
    out = cv2.erode(
        a.astype(np.uint8),
        _SQUARE,
        iterations=iterations,
        borderType=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return out.astype(bool)


def _fill_holes(a):
    """ndimage.binary_fill_holes: background not 4-connected to the image border is filled."""
    labels, _ = ndimage.label(~a)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    outside = np.zeros(labels.max() + 1, bool)
    outside[border] = True
    outside[0] = False
    return ~outside[labels]
