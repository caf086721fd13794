"""Radiometric normalisation: object radiance divided by the reference (flat-field) radiance.

The Digital Hammurabi scanner divides every object image by the image of a flat white
target taken under the very same lighting ("background" image).  With the instrument model
of SCAN_BUNDLE.md,

    L_obj(p) = k · ρ(p) · E(p′) · V · max(0, n·l)        (object, surface point at height h)
    L_ref(p) = k · ρ_ref · E(p) · cos θ                   (flat target, n_ref·l = cos θ)

so that, when E(p′) ≈ E(p),

    s(p) = L_obj / L_ref · ρ_ref · cos θ = ρ · V · max(0, n·l).

``s`` is the "shading" consumed by photometric stereo and colour recovery: the unknown source
power k and its non-uniform footprint E cancel pixel by pixel.
"""

from __future__ import annotations

import numpy as np

from worker.recon.parallel import run_blocks

__all__ = ["flat_field"]


def _as_stack(name: str, array: np.ndarray) -> np.ndarray:
    arr = np.asarray(array)
    if arr.ndim not in (2, 3):
        raise ValueError(f"{name} must be (H, W) or (K, H, W), got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise ValueError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    return arr


def flat_field(
    object_radiance: np.ndarray,
    reference_radiance: np.ndarray,
    *,
    reference_reflectance: float,
    polar_deg: float | np.ndarray,
    min_reference_fraction: float = 0.05,
    workers: int = 1,
) -> np.ndarray:
    """Shading ``s = ρ·V·max(0, n·l)`` from object and reference radiance.

    Parameters
    ----------
    object_radiance, reference_radiance : (H, W) or (K, H, W) array
        Linear, dark-corrected radiance of the object frames and of their matching reference
        frames (same kind, azimuth, polar angle, channel).  Any common scale.
    reference_reflectance : float in (0, 1]
        Diffuse reflectance ρ_ref of the white target (``reference.reflectance``), so that the
        result is relative to a perfect white.
    polar_deg : float or (K,) array, degrees in (0, 90)
        Polar angle θ of the source of each frame; the flat target receives ``cos θ``.
    min_reference_fraction : float in [0, 1)
        Pixels whose reference radiance is below this fraction of the frame's bright level
        (its 99th percentile) are NaN: the source barely reaches them, the ratio is noise.
    workers : int
        Threads sharing the frames (the result does not depend on it).

    Returns
    -------
    (H, W) or (K, H, W) float32
        ``s = (L_obj / L_ref) · ρ_ref · cos θ``; dimensionless, 1 for a perfect white surface
        facing the source.  NaN where the reference is too dark or either input is not finite.

    Notes
    -----
    The division assumes E(p′) ≈ E(p): the object point at height h is lit by the ray that
    crosses the reference plane at p′ = p − h·tanθ·u, whereas the reference pixel measures E
    at p.  The source footprint varies slowly (a lamp or projector illuminates the whole field;
    E changes over millimetres to centimetres) while h·tanθ is at most a few millimetres, so
    the relative error is |∇E|/E · h·tanθ, i.e. a few per cent at worst.  It fails where E has
    structure at the scale of h·tanθ: the edge of the illuminated field, vignetting of the
    projector, dust or scratches on the source optics, and — for fringe frames — the pattern
    itself (never flat-field fringe frames with this function; their phase is compared, not
    their intensity).  The shadow factor V and the attached shadow max(0, n·l) are not removed:
    photometric stereo must reject those samples.
    """
    obj = _as_stack("object_radiance", object_radiance)
    ref = _as_stack("reference_radiance", reference_radiance)
    if obj.shape != ref.shape:
        raise ValueError(
            f"reference_radiance shape {ref.shape} differs from object_radiance shape {obj.shape}"
        )
    rho_ref = float(reference_reflectance)
    if not (0.0 < rho_ref <= 1.0):
        raise ValueError(f"reference_reflectance must lie in (0, 1], got {reference_reflectance}")
    if not (0.0 <= float(min_reference_fraction) < 1.0):
        raise ValueError(f"min_reference_fraction must lie in [0, 1), got {min_reference_fraction}")
    theta = np.asarray(polar_deg, dtype=np.float64)
    k = 1 if obj.ndim == 2 else obj.shape[0]
    if theta.ndim == 0:
        theta = np.full(k, float(theta))
    if theta.shape != (k,):
        raise ValueError(f"polar_deg must be a scalar or have shape ({k},), got {theta.shape}")
    if not np.all((theta > 0.0) & (theta < 90.0)):
        raise ValueError("polar_deg must lie in (0, 90) degrees")

    obj3 = obj.reshape((k,) + obj.shape[-2:]).astype(np.float32, copy=False)
    ref3 = ref.reshape((k,) + ref.shape[-2:]).astype(np.float32, copy=False)
    out = np.empty(obj3.shape, dtype=np.float32)

    def frame(i: int) -> None:
        r = ref3[i]
        # A strided sample gives the bright level at a sixteenth of the cost.
        sample = r[::4, ::4]
        sample = sample[np.isfinite(sample)]
        bright = float(np.percentile(sample, 99.0)) if sample.size else 0.0
        if bright <= 0.0:
            out[i] = np.nan
            return
        scale = np.float32(rho_ref * np.cos(np.deg2rad(theta[i])))
        # Straight into the output, in place: a frame's temporaries cost more than its
        # arithmetic, and np.where's per-element branch several times more.
        s = out[i]
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(obj3[i], r, out=s)
            s *= scale
        # The threshold is ≥ 0 (bright > 0): above it, r > 0 too.
        ok = r > np.float32(min_reference_fraction * bright)
        ok &= np.isfinite(r)
        ok &= np.isfinite(s)
        np.copyto(s, np.float32(np.nan), where=~ok)

    run_blocks(frame, range(k), workers=workers)
    return out.reshape(obj.shape)
