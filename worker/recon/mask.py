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
   and, with the pixel size, a support whose faces rise toward the image border (a
   V-block's) is found by its geometry: the heights split into smooth regions along
   cliffs no clay side or support face makes continuously (`_support_below_cliff`), and
   a region that reaches the image border and lies below the ground across its cliff is
   the support; where the heights find a support and the brightness class holds more
   than half of it (clay and support overlap in brightness: dark clay on a light cloth),
   the geometry decides the whole mask, not only where the support is;
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
    pixel_size_um: float | None = None,
) -> np.ndarray:
    """Boolean (H, W) mask of the tablet.

    brightness: (H, W) albedo relative to white (or any brightness proportional to it), NaN
    where unknown. has_normal, has_height: (H, W) bool, where a normal / fringe height exists.
    modulation: (H, W) fringe modulation B/A (NaN allowed). height_um: (H, W) µm (NaN allowed).
    pixel_size_um: with height_um, enables the support's cliff test (`_support_below_cliff`).
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
        # Brightness is the finer cue (a sloping rim falls below any height threshold) as
        # long as it tells the support from the clay. Where the heights find the support
        # and brightness puts most of it in the tablet's class, the two populations overlap
        # in brightness (a light cloth or V-block; dark clay): a dark patch of clay is then
        # as likely to fall below Otsu's threshold as a bright patch of support above it,
        # and the geometry decides the whole mask. Between the two (brightness takes some
        # of the support) the evidence is mixed: brightness keeps its mask, less the
        # support.
        bright = fg
        raised = _raised_above_support(height_um, finite & measured)
        if raised is not None:
            lower = finite & measured & ~raised
            overlap = (raised & fg).sum() < 0.5 * (raised | fg).sum()
            if overlap or _confuses(bright, lower):
                # A support as bright as the clay (a light V-block or cloth) that stands
                # apart in height: the tablet is what stands above it. Where the two agree
                # (IoU ≥ ½) brightness keeps its finer rim.
                fg = raised & finite & (b > 0.5 * min_albedo)
        if pixel_size_um is not None:
            support = _support_below_cliff(
                height_um, finite & measured, pixel_size_um=pixel_size_um
            )
            if support is not None:
                if (fg & ~support).sum() < 0.5 * fg.sum() or _confuses(bright, support):
                    # Brightness picked mostly the support (brighter than the clay, as a
                    # light V-block is), or cannot tell the two apart: the tablet is what
                    # the geometry leaves.
                    fg = finite & measured & (b > 0.5 * min_albedo)
                    # A pixel without a height has no geometry: next to the support (in
                    # the tablet's shadow, where the fringes left the support unmeasured)
                    # it goes with the support, one pixel deep.
                    support = support | (_dilate(support, 1) & ~np.isfinite(height_um))
                fg &= ~support
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


def _confuses(bright: np.ndarray, support: np.ndarray, *, share: float = 0.5) -> bool:
    """Whether the brightness class `bright` holds more than `share` of the `support` that
    the heights found: brightness then does not tell the support from the clay."""
    n = int(np.count_nonzero(support))
    return n > 0 and int(np.count_nonzero(bright & support)) > share * n


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


def _support_below_cliff(
    height_um,
    where,
    *,
    pixel_size_um: float,
    step_um: float = 150.0,
    border_share: float = 0.25,
    lower_share: float = 0.75,
):
    """The pixels of a support seen around the tablet, told by its geometry, or None.

    A tablet rests on its support, so along its silhouette the heights climb from the
    support up the tablet's side more steeply than any support face does. Edges between
    4-neighbours whose height step exceeds max(`step_um`, 2·s) (steeper than 63°) are cut,
    the pixels at a cut set aside, and the rest split into connected regions; each set-aside
    pixel then joins the region nearest to it. A region is support when it reaches the
    image border (a 4 px band) with at least `border_share` of the measured border pixels,
    and it is the lower side of at least `lower_share` of the edges it shares with other
    regions, by more than half the step in the median (the set-aside pixels nearest to it
    count only within a step of its edge's level). A tablet filling the frame has no
    ground above its border regions; a chip inside it does not reach the border. None when
    no region passes or nothing would be left.
    """
    h = np.asarray(height_um, np.float32)
    ok = np.asarray(where, bool) & np.isfinite(h)
    if ok.sum() < 64 or min(h.shape) < 16:
        return None
    step = max(float(step_um), 2.0 * float(pixel_size_um))
    with np.errstate(invalid="ignore"):
        cut_x = ok[:, 1:] & ok[:, :-1] & (np.abs(h[:, 1:] - h[:, :-1]) > step)
        cut_y = ok[1:, :] & ok[:-1, :] & (np.abs(h[1:, :] - h[:-1, :]) > step)
    cliff = np.zeros(h.shape, bool)
    cliff[:, 1:] |= cut_x
    cliff[:, :-1] |= cut_x
    cliff[1:, :] |= cut_y
    cliff[:-1, :] |= cut_y
    if not cliff.any():
        return None
    labels, count = ndimage.label(ok & ~cliff)
    if count < 2:
        return None
    border = np.ones(h.shape, bool)
    border[4:-4, 4:-4] = False
    measured_border = int(np.count_nonzero(border & ok))
    on_border = np.bincount(labels[border].ravel(), minlength=count + 1)
    candidates = np.nonzero(on_border[1:] >= border_share * max(measured_border, 1))[0] + 1
    if measured_border < 16 or candidates.size == 0:
        return None
    # Every set-aside pixel joins its nearest region.
    idx = ndimage.distance_transform_edt(labels == 0, return_distances=False, return_indices=True)
    lab = np.where(ok, labels[idx[0], idx[1]], 0)
    below = np.zeros(count + 1)
    shared = np.zeros(count + 1)
    rise: dict[int, list] = {int(c): [] for c in candidates}
    for a, b, ha, hb in (
        (lab[:, :-1], lab[:, 1:], h[:, :-1], h[:, 1:]),
        (lab[:-1, :], lab[1:, :], h[:-1, :], h[1:, :]),
    ):
        e = (a > 0) & (b > 0) & (a != b)
        la, lb, d = a[e], b[e], (hb - ha)[e]  # d: how far b's side stands above a's
        for side, other_rise in ((la, d), (lb, -d)):
            shared += np.bincount(side, minlength=count + 1)
            below += np.bincount(side, weights=other_rise > 0, minlength=count + 1)
            for c in rise:
                rise[c].append(other_rise[side == c])
    support = np.zeros(h.shape, bool)
    for c, parts in rise.items():
        r = np.concatenate(parts)
        if r.size and below[c] >= lower_share * shared[c] and np.median(r) > 0.5 * step:
            # A set-aside pixel nearest to the support is support only within a step of
            # the support's own edge (the tablet's steep side is tablet, however near).
            core = labels == c
            edge = core & cv2.dilate(cliff.astype(np.uint8), _SQUARE).astype(bool)
            top = float(np.median(h[edge] if edge.any() else h[core])) + step
            with np.errstate(invalid="ignore"):
                support |= core | ((lab == c) & cliff & (h <= top))
    if not support.any():
        return None
    if (ok & ~support).sum() < 0.05 * ok.sum():
        return None
    return support


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
