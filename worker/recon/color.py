"""Colour: RGB reflectance from red/green/blue frames given the normals, and sRGB encoding.

A colour frame of primary c at azimuth φ_k measures, after the flat field (reference target
under the same coloured light; :func:`worker.recon.radiometry.flat_field`),

    s_k = ρ_c · V_k · max(0, n·l_k),

so each sample with a lit, well-inclined source gives ρ_c = s_k / (n·l_k), relative to a
perfect white (the reference reflectance is applied by the flat field).  Samples are combined
per pixel and channel robustly: only n·l_k ≥ ``min_cos`` (division by a small cosine amplifies
noise and normal errors), then the sample that most others agree with (a consensus centre:
cast shadows and highlights agree with nobody), then the mean of the samples within a band
around it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ColorResult", "grey_reflectance", "linear_to_srgb8", "rgb_reflectance"]

_CHANNELS = {"red": 0, "green": 1, "blue": 2}
# Pixels per block of the per-pixel work: a block's (A, n) arrays stay in cache.
_BLOCK_PIXELS = 1 << 16


@dataclass(frozen=True)
class ColorResult:
    """Output of :func:`rgb_reflectance`.

    rgb : (H, W, 3) float32, linear reflectance (0…1 for real surfaces), NaN where unknown
        and no fallback was given.
    samples_used : (H, W, 3) int16, samples averaged per channel (0 where the fallback or
        NaN was used).
    fallback : (H, W) bool, pixels that took the grey fallback.
    """

    rgb: np.ndarray
    samples_used: np.ndarray
    fallback: np.ndarray


def _consensus_centre(est: np.ndarray, band: float) -> np.ndarray:
    """Per pixel, the sample with the most samples within ±band of it (relative).

    A mode rather than a mean or median: a cast shadow and a highlight each agree with
    nobody, whereas clean samples agree with each other.  Ties go to the lower estimate, so
    that with one clean sample and one highlight the clean one wins (shadows were already
    dropped as too dark).  est : (A, N) with NaN for unusable samples.
    """
    a = est.shape[0]
    finite = np.isfinite(est)
    # support[j] = #{i : |est_i − est_j| ≤ band·est_j, both finite}. |est_i − est_j| is
    # symmetric: each pair is differenced once and tested against both ends.
    d = np.empty(est.shape[1], np.float32)
    with np.errstate(invalid="ignore"):
        tol = [band * est[j] for j in range(a)]
        support = [(finite[j] & (np.float32(0) <= tol[j])).astype(np.int16) for j in range(a)]
        for i in range(a):
            for j in range(i + 1, a):
                np.abs(np.subtract(est[j], est[i], out=d), out=d)
                support[i] += d <= tol[i]
                support[j] += d <= tol[j]
    # A non-finite sample neither has support nor gives it (inf − inf is NaN, inf ≤ inf).
    for j in range(a):
        support[j] *= finite[j]
    # Masked copies rather than np.where, whose per-element branch is the slower.
    best = np.full(est.shape[1], np.nan, dtype=np.float32)
    best_support = np.zeros(est.shape[1], dtype=np.int16)
    for j in range(a):
        c = est[j]
        with np.errstate(invalid="ignore"):
            better = (support[j] > best_support) | (
                (support[j] == best_support) & (support[j] > 0) & (c < best)
            )
        np.copyto(best, c, where=better)
        np.copyto(best_support, support[j], where=better)
    return best


def _channel_reflectance(sc, ls, nt, min_cos, band, min_reflectance):
    """Reflectance of one channel and the samples averaged, (n,) each, from its (A, n)
    shading ``sc``, its (A, 3) light directions ``ls`` and the (3, n) normals ``nt``."""
    # n·l as three multiply-adds, (A, n): as fast as BLAS, whose threads would spin
    # beside the stages that run concurrently with this one.
    cos = ls[:, :1] * nt[0]
    cos += ls[:, 1:2] * nt[1]
    cos += ls[:, 2:3] * nt[2]
    est = np.full(sc.shape, np.nan, np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(sc, cos, out=est, where=cos >= min_cos)
        # A cast shadow leaves ρ ≈ 0 (noise only): below min_reflectance nothing is usable.
        np.copyto(est, np.float32(np.nan), where=~(est >= min_reflectance))
    centre = _consensus_centre(est, band)
    # Samples within the band around the centre (a NaN sample or centre compares False;
    # the centre is finite wherever it has support), summed in sample order.
    tol = band * centre
    total = np.zeros(centre.shape, np.float32)
    cnt = np.zeros(centre.shape, np.int16)
    d = np.empty(centre.shape, np.float32)
    for j in range(sc.shape[0]):
        with np.errstate(invalid="ignore"):
            keep = np.abs(np.subtract(est[j], centre, out=d), out=d) <= tol
        cnt += keep
        np.add(total, est[j], out=total, where=keep)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(cnt > 0, total / cnt, np.float32(np.nan)), cnt


def _channel_index(channel) -> np.ndarray:
    out = []
    for c in channel:
        if isinstance(c, str) and c in _CHANNELS:
            out.append(_CHANNELS[c])
        elif isinstance(c, (int, np.integer)) and not isinstance(c, bool) and 0 <= c <= 2:
            out.append(int(c))
        else:
            raise ValueError(f"channel entries must be 'red', 'green', 'blue' or 0-2, got {c!r}")
    return np.asarray(out, dtype=np.int64)


def rgb_reflectance(
    shading: np.ndarray,
    channel,
    light_dirs: np.ndarray,
    normals: np.ndarray,
    *,
    min_cos: float = 0.3,
    band: float = 0.3,
    min_reflectance: float = 0.02,
    fallback_albedo: np.ndarray | None = None,
) -> ColorResult:
    """Robust per-channel reflectance ρ_c = s/(n·l) averaged over the colour frames.

    Parameters
    ----------
    shading : (K, H, W) float
        Flat-fielded colour frames (any azimuths and channels, in any order).
    channel : sequence of K of 'red' | 'green' | 'blue' (or 0, 1, 2)
    light_dirs : (K, 3) float
        Source directions (:func:`worker.recon.photometric.light_directions`).
    normals : (H, W, 3) float
        Unit normals (photometric stereo), NaN where unknown.
    min_cos : float
        Smallest n·l used.
    band : float
        Samples within (1 ± band)·centre are averaged, the centre being the sample most
        others agree with; the rest are shadows or highlights.
    min_reflectance : float
        Estimates below this are cast shadows (2 % is darker than fired or unfired clay).
    fallback_albedo : (H, W) float, optional
        Photometric albedo; pixels missing any channel become grey (ρ, ρ, ρ).
    """
    s = np.asarray(shading, dtype=np.float32)
    if s.ndim != 3:
        raise ValueError(f"shading must have shape (K, H, W), got {s.shape}")
    k, h, w = s.shape
    ch = _channel_index(channel)
    if ch.shape != (k,):
        raise ValueError(f"channel must have {k} entries, got {ch.shape[0]}")
    lights = np.asarray(light_dirs, dtype=np.float32)
    if lights.shape != (k, 3):
        raise ValueError(f"light_dirs must have shape ({k}, 3), got {lights.shape}")
    n = np.asarray(normals, dtype=np.float32)
    if n.shape != (h, w, 3):
        raise ValueError(f"normals must have shape ({h}, {w}, 3), got {n.shape}")
    if not (0.0 < min_cos < 1.0):
        raise ValueError(f"min_cos must lie in (0, 1), got {min_cos}")
    if not (0.0 <= min_reflectance < 1.0):
        raise ValueError(f"min_reflectance must lie in [0, 1), got {min_reflectance}")
    if not (0.0 < band < 1.0):
        raise ValueError(f"band must lie in (0, 1), got {band}")
    if fallback_albedo is not None:
        fallback_albedo = np.asarray(fallback_albedo, dtype=np.float32)
        if fallback_albedo.shape != (h, w):
            raise ValueError(f"fallback_albedo must have shape ({h}, {w})")

    rgb = np.full((3, h * w), np.nan, dtype=np.float32)
    used = np.zeros((3, h * w), dtype=np.int16)
    nt = np.ascontiguousarray(n.reshape(-1, 3).T)
    s_flat = s.reshape(k, h * w)
    for c in range(3):
        sel = np.flatnonzero(ch == c)
        if sel.size == 0:
            continue
        # Pixels are independent: the work runs block by block, in cache.
        for start in range(0, h * w, _BLOCK_PIXELS):
            px = slice(start, start + _BLOCK_PIXELS)
            rgb[c, px], used[c, px] = _channel_reflectance(
                s_flat[sel, px], lights[sel], nt[:, px], min_cos, band, min_reflectance
            )
    missing = np.any(~np.isfinite(rgb), axis=0)
    fallback = np.zeros(h * w, dtype=bool)
    if fallback_albedo is not None:
        fallback = missing & np.isfinite(fallback_albedo.ravel())
        rgb[:, fallback] = fallback_albedo.ravel()[fallback]
        used[:, fallback] = 0
    return ColorResult(
        rgb=np.moveaxis(rgb.reshape(3, h, w), 0, -1).copy(),
        samples_used=np.moveaxis(used.reshape(3, h, w), 0, -1).copy(),
        fallback=fallback.reshape(h, w),
    )


def grey_reflectance(albedo: np.ndarray) -> np.ndarray:
    """(H, W) albedo → (H, W, 3) float32 grey reflectance, for bundles without colour frames."""
    a = np.asarray(albedo, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"albedo must be 2-D, got shape {a.shape}")
    return np.repeat(a[..., None], 3, axis=-1)


# float32 values of [0, 1] in buckets by the top 20 bits of their pattern (11 mantissa bits,
# a relative width of 2^-11 ≈ 0.05 %): an 8-bit sRGB code spans at least 0.08 % of L (just
# above L = 0.0031308), so a bucket holds at most one code boundary.
_SRGB_BUCKET_SHIFT = 12


def _srgb8(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function of linear values in [0, 1], as 8-bit codes:
    V = 12.92·L for L ≤ 0.0031308, else 1.055·L^(1/2.4) − 0.055; then round(255·V)."""
    x = np.asarray(x, dtype=np.float64)
    v = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(255.0 * v).astype(np.uint8)


def _srgb8_table():
    """Per bucket of float32 patterns (see _SRGB_BUCKET_SHIFT): the code at its start and
    the least value in it with the next code (+inf if none), or None if a bucket held two
    boundaries.  The code of L is then ``start[b] + (L >= boundary[b])``, bit for bit
    :func:`_srgb8` of L since the code never decreases with L (checked over every float32
    of [0, 1])."""
    one = int(np.float32(1.0).view(np.int32))
    # Each code's least float32, by bisection over the patterns (ordered like the values).
    codes = np.arange(1, 256)
    lo, hi = np.zeros(codes.size, np.int64), np.full(codes.size, one, np.int64)
    while np.any(lo < hi):
        mid = (lo + hi) // 2
        up = _srgb8(mid.astype(np.int32).view(np.float32)) >= codes
        lo, hi = np.where(up, lo, mid + 1), np.where(up, mid, hi)
    bucket = lo >> _SRGB_BUCKET_SHIFT
    n_buckets = (one >> _SRGB_BUCKET_SHIFT) + 1
    per_bucket = np.bincount(bucket, minlength=n_buckets)
    if per_bucket.max() > 1:
        return None
    start = (np.cumsum(per_bucket) - per_bucket).astype(np.uint8)
    boundary = np.full(n_buckets, np.inf, np.float32)
    boundary[bucket] = lo.astype(np.int32).view(np.float32)
    return start, boundary


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear reflectance → 8-bit sRGB (IEC 61966-2-1 transfer function).

    Values are clipped to [0, 1]; NaN becomes 0.  V = 12.92·L for L ≤ 0.0031308, else
    1.055·L^(1/2.4) − 0.055; then round(255·V).  Any shape; returns uint8 of the same shape.
    float32 input (the reflectance maps) is encoded by table, bit for bit the same codes at
    a fraction of the cost of a float64 power per value.
    """
    x = np.asarray(rgb)
    table = _srgb8_table() if x.dtype == np.float32 else None
    if table is None:
        x = np.asarray(x, dtype=np.float64)
        return _srgb8(np.clip(np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0))
    start, boundary = table
    # fmax takes NaN to 0 as well (np.nan_to_num is several times slower than both passes).
    y = np.fmax(x, np.float32(0.0))
    np.minimum(y, np.float32(1.0), out=y)
    # −0.0 has the sign bit set: its negative pattern goes to bucket 0 with +0.0.
    b = np.maximum(y.view(np.int32) >> _SRGB_BUCKET_SHIFT, 0)
    code = start.take(b)
    code += y >= boundary.take(b)
    return code
