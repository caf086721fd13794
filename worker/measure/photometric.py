"""Stages 1–3 from a bundle: flat-fielded shading, photometric normals, colour."""

from __future__ import annotations

import cv2
import numpy as np

from worker.measure.frames import angle_key
from worker.recon.color import rgb_reflectance
from worker.recon.photometric import PhotometricResult, light_directions, photometric_stereo
from worker.recon.radiometry import flat_field

__all__ = ["measure_color", "measure_photometric"]

HIGHLIGHT_CONE_DEG = 20.0


def _source_footprint(ref_stack, frames, height_um, pixel_size_um):
    """Reference radiance at p′ = p − h·tanθ·u instead of p (in place).

    The light that reaches the surface point above p crossed the reference plane at p′
    (SCAN_BUNDLE.md): with a non-uniform source the flat field must be read there, or the
    shading of each light is off by E(p′)/E(p), a few per cent per millimetre of height,
    which tilts the normals by about a degree.
    """
    rows, cols = height_um.shape
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float32)
    for k, f in enumerate(frames):
        shift = height_um * np.float32(np.tan(np.radians(f.polar_deg)) / pixel_size_um)
        phi = np.radians(f.azimuth_deg)
        map_x = c - shift * np.float32(np.sin(phi))
        map_y = r - shift * np.float32(np.cos(phi))
        ref_stack[k] = cv2.remap(
            ref_stack[k],
            map_x,
            map_y,
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return ref_stack


def _shading(bundle, frames, stack, rho_ref, meas, kind):
    refs = [bundle.reference_of(f) for f in frames]
    if all(r is not None for r in refs):
        polar = np.array([f.polar_deg for f in frames], np.float64)
        ref_stack = bundle.radiance_many(refs)
        if meas.rough_height_um is not None:
            ref_stack = _source_footprint(
                ref_stack, frames, meas.rough_height_um, meas.pixel_size_um
            )
        return flat_field(stack, ref_stack, reference_reflectance=rho_ref, polar_deg=polar)
    meas.warnings.append(
        f"{kind}: no reference frames; assuming uniform illumination, albedo is relative"
    )
    # Without a flat field: L ∝ ρ·E·max(0, n·l) with E the same for every source (a source
    # of another power says so by its frame's exposure, which radiance is divided by), so
    # s = L / (bright level), one scale for all frames: their ratios carry the normals.  No
    # cos θ: that is the reference target's n·l, not the object's.
    scale = float(np.nanpercentile(stack, 99.5)) or 1.0
    return (stack / np.float32(scale)).astype(np.float32)


def measure_photometric(bundle, photo, meas, rho_ref):
    stack = bundle.radiance_many(photo)
    shading = _shading(bundle, photo, stack, rho_ref, meas, "photometric")
    del stack
    az = np.array([f.azimuth_deg for f in photo])
    polar = np.array([f.polar_deg for f in photo])
    lights = light_directions(az, polar)
    res = _without_highlights(shading, lights, photometric_stereo(shading, lights))
    meas.normals = res.normals
    meas.albedo = res.albedo
    meas.residual = res.residual
    meas.lights_used = res.lights_used
    meas.photometric_polar_deg = float(np.median(polar))
    meas.used["photometric_azimuths_deg"] = sorted({angle_key(a) for a in az})


def _without_highlights(shading, lights, first, *, cone_deg=HIGHLIGHT_CONE_DEG, k_sigma=1.5):
    """Solve again without the samples seen near the mirror direction of their light, where
    those samples prove to be highlights.

    A glossy surface (fired clay, consolidants) adds a highlight where the normal is near
    the half vector h_k = (l_k + v)/|l_k + v| of light k and the camera direction v =
    (0, 0, −1). Highlights a few per cent above the Lambertian shading pass any outlier test
    yet tilt the normal by a degree or more; the geometry tells where they can be. The
    samples within `cone_deg` of the mirror direction that lie above the first fit are left
    out (NaN) and the pixel solved again from the others (three suffice). A highlight only
    adds light, so the new solution is kept only where the left-out samples sit above it:
    their mean excess over it exceeds `k_sigma` standard errors of the shading noise. On a
    matte surface that happens by chance for ~7 % of the pixels (1.5σ: a fit on fewer
    lights, still unbiased), whatever the number of lights, their polar angles or the lobe's
    width. The standard error includes the new fit's own uncertainty at the left-out
    directions, so a re-solve that extrapolates from a few grazing lights needs more proof.
    The 20° cone is where a Blinn–Phong lobe of exponent 40 still exceeds 8 % of its peak;
    wider cones cost accuracy on our simulated scans (25°, 30°: median 0.67° → 0.71°, 0.73°),
    broad lobes are the robust fit's business (`photometric_fit.mirror_trim`).
    """
    sigma = float(first.noise_sigma)
    if not sigma > 0:
        return first
    k, h, w = shading.shape
    half = lights + np.array([0.0, 0.0, -1.0])
    half = (half / np.linalg.norm(half, axis=1, keepdims=True)).astype(np.float32)
    lights32 = lights.astype(np.float32)
    # Everything below runs on the solved pixels only, as (K, n) columns.
    normals = first.normals.reshape(-1, 3)
    pix = np.flatnonzero(np.isfinite(normals[:, 0]))
    n = normals[pix]
    s = shading.reshape(k, -1)[:, pix]
    finite = np.isfinite(s)
    # With four inliers or fewer the fit bends to a highlight until its residual says little
    # (leverage near 1; with three it is zero) and its normal may be off by degrees: there
    # the cone is widened by 10° and every sample in it is a suspect.
    few = first.lights_used.ravel()[pix] <= 4
    cone_cos = np.where(few, np.cos(np.radians(cone_deg + 10.0)), np.cos(np.radians(cone_deg)))
    near = (half @ n.T > cone_cos.astype(np.float32)) & finite
    b = n * first.albedo.ravel()[pix, None]
    with np.errstate(invalid="ignore"):
        suspect = near & ((s - lights32 @ b.T > np.float32(sigma)) | few)
    redo = np.any(suspect, axis=0) & (np.sum(finite & ~near, axis=0) >= 3)
    if not redo.any():
        return first
    pix, s, near = pix[redo], s[:, redo], near[:, redo]
    cleaned = np.where(near, np.float32(np.nan), s)
    second = photometric_stereo(cleaned[:, None, :], lights, noise_sigma=sigma)
    b2 = (second.normals * second.albedo[..., None]).reshape(-1, 3)
    ok = np.isfinite(b2[:, 0])
    b2 = np.where(ok[:, None], b2, np.float32(0.0))
    pred = lights @ b2.T
    excess = np.where(near, s - pred, 0.0).sum(axis=0)
    m = near.sum(axis=0)
    # The standard error of the mean excess: noise of the m samples plus that of the new
    # fit's prediction at their mean direction ū, σ²·ūᵀM⁻¹ū with M = Σ l lᵀ over the lights
    # in front of it (an extrapolation from grazing lights is uncertain).
    front = np.isfinite(s) & ~near & (pred > 0.1 * np.linalg.norm(b2, axis=1))
    iu = np.triu_indices(3)
    mm6 = front.T.astype(np.float64) @ (lights[:, :, None] * lights[:, None, :])[:, iu[0], iu[1]]
    mm = mm6[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    u = (near.T.astype(np.float64) @ lights) / m[:, None]
    ok &= np.linalg.det(mm) > 1e-9
    mm[~ok] = np.eye(3)
    spread = np.einsum("ni,ni->n", u, np.linalg.solve(mm, u[..., None])[..., 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        z = excess / m / (sigma * np.sqrt(1.0 / m + spread))
    ok &= z > k_sigma
    pix = pix[ok]

    def merged(a, b):
        out = a.reshape(h * w, -1).copy()
        out[pix] = b.reshape(-1, out.shape[1])[ok]
        return out.reshape(a.shape)

    return PhotometricResult(
        normals=merged(first.normals, second.normals),
        albedo=merged(first.albedo, second.albedo),
        residual=merged(first.residual, second.residual),
        lights_used=merged(first.lights_used, second.lights_used),
        noise_sigma=sigma,
    )


def measure_color(bundle, color, meas, rho_ref):
    if meas.normals is None:
        meas.warnings.append("color: frames ignored (no normals to divide the shading by)")
        return
    stack = bundle.radiance_many(color)
    shading = _shading(bundle, color, stack, rho_ref, meas, "color")
    del stack
    az = np.array([f.azimuth_deg for f in color])
    polar = np.array([f.polar_deg for f in color])
    res = rgb_reflectance(
        shading,
        [f.channel for f in color],
        light_directions(az, polar),
        meas.normals,
        fallback_albedo=meas.albedo,
    )
    meas.rgb_linear = res.rgb
    meas.used["color_azimuths_deg"] = sorted({angle_key(a) for a in az})
    meas.used["color_channels"] = sorted({f.channel for f in color})
