"""The ideal instrument of SCAN_BUNDLE.md ("What a pixel measures") plus its imperfections.

For a frame lit from azimuth φ at polar angle θ (u = (sin φ, cos φ),
l = (sin θ sin φ, sin θ cos φ, -cos θ)), at every sample p of the view with height h:

    p' = p - h·tan θ·u                      (where the light ray meets the reference plane)
    L  = E(p')·V·[ρ·max(0, n·l) + k_s·max(0, n·ĥ)^α]·(1 + m·cos(2π (u·p')/P + δ + δ₀))

with E the source's smooth non-uniform irradiance (different per source and azimuth),
V the cast-shadow visibility, ρ the reflectance (grey = mean of RGB for white light, one
channel for colour frames), a Blinn–Phong lobe (ĥ the half vector toward the camera),
the fringe factor only for fringe frames, and δ₀ an unknown phase offset per azimuth,
polar angle and period. The reference target is the same light on a flat matte white
target at h = 0. Samples are box-averaged over each pixel, stray light is added, and
the image is blurred by the camera's Gaussian PSF.

``Rig.physics`` (``physics.py``) adds what the ideal model leaves out: the projector's
profile (``projector.py``) with phase-step errors and a modulation that varies per
azimuth and across the field, light scattered in the clay, specular lobes,
interreflection and a veil, hot pixels, and camera overrides. Its default, the ideal
instrument, leaves every frame bit for bit as above.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

from worker.simulate.noise import NoiseModel, encode_frame, fixed_pattern_e
from worker.simulate.physics import IDEAL, Physics
from worker.simulate.projector import fringe_profile
from worker.simulate.shadow import cast_shadow
from worker.simulate.view import View, box_mean, sample_coords_um

__all__ = ["CHANNELS", "FrameSpec", "Rig", "frame_radiance", "render_frame"]

CHANNELS = ("red", "green", "blue")
KINDS = ("dark", "photometric", "color", "fringe")


@dataclass(frozen=True)
class FrameSpec:
    """One frame to acquire, with the fields of a bundle frame (SCAN_BUNDLE.md)."""

    kind: str
    target: str = "object"
    azimuth_deg: float | None = None
    polar_deg: float = 45.0
    channel: str | None = None
    period_um: float | None = None
    phase_deg: float | None = None
    exposure: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")
        if self.target not in ("object", "reference"):
            raise ValueError(f"target must be 'object' or 'reference', got {self.target!r}")
        if self.kind != "dark" and self.azimuth_deg is None:
            raise ValueError(f"azimuth_deg is required for {self.kind} frames")
        if not 0 < self.polar_deg < 90:
            raise ValueError(f"polar_deg must be in (0, 90), got {self.polar_deg}")
        if self.kind == "color" and self.channel not in CHANNELS:
            raise ValueError(f"channel must be one of {CHANNELS} for color frames")
        if self.kind == "fringe" and (self.period_um is None or self.period_um <= 0):
            raise ValueError("period_um must be > 0 for fringe frames")
        if self.kind == "fringe" and self.phase_deg is None:
            raise ValueError("phase_deg is required for fringe frames")
        if self.exposure <= 0:
            raise ValueError(f"exposure must be > 0, got {self.exposure}")


def _key(*values: float) -> list[int]:
    return [int(round(v * 1000)) % (1 << 62) for v in values]


@dataclass(frozen=True)
class Rig:
    """Hidden properties of the instrument: source non-uniformity, fringe phase offsets,
    channel gains and the camera's fixed pattern, all drawn from ``seed``.

    field_*_um: the camera's field of view (the irradiance polynomial is defined on it).
    """

    seed: int
    field_width_um: float
    field_height_um: float
    irradiance_variation: float = 0.15
    source_radiance: float = 0.6  # radiance of a white diffuser facing the source, E = 1
    reflectance_reference: float = 0.95
    channel_gain: tuple[float, float, float] = (1.0, 0.85, 0.7)
    physics: Physics = IDEAL
    _offsets: dict = field(default_factory=dict, repr=False, compare=False)

    def irradiance(
        self, source: str, azimuth_deg: float, polar_deg: float, x_um: np.ndarray, y_um: np.ndarray
    ) -> np.ndarray:
        """E(p') (relative, about 1 ± irradiance_variation) of a source on the reference plane.

        A quadratic in the normalised field coordinates whose linear part falls off away from
        the source; coefficients drawn per (source, azimuth, polar angle).
        """
        source_id = {"lamp": 1, "projector": 2}[source]
        rng = np.random.default_rng([self.seed, source_id, *_key(azimuth_deg % 360, polar_deg)])
        c = rng.uniform(-1, 1, 5) * np.array([0.5, 0.5, 0.25, 0.25, 0.25])
        phi = np.radians(azimuth_deg)
        c[0] = 0.5 * c[0] + 0.5 * np.sin(phi)
        c[1] = 0.5 * c[1] + 0.5 * np.cos(phi)
        scale = self.irradiance_variation / np.sum(np.abs(c))
        xn = (x_um - self.field_width_um / 2) / (self.field_width_um / 2)
        yn = (y_um - self.field_height_um / 2) / (self.field_height_um / 2)
        poly = c[0] * xn + c[1] * yn + c[2] * xn * xn + c[3] * yn * yn + c[4] * xn * yn
        return 1.0 + scale * poly

    def phase_offset(self, azimuth_deg: float, polar_deg: float, period_um: float) -> float:
        """The projector's unknown constant phase δ₀ (rad) for an azimuth, polar angle and period."""
        rng = np.random.default_rng(
            [self.seed, 0xF41, *_key(azimuth_deg % 360, polar_deg, period_um)]
        )
        return float(rng.uniform(0, 2 * np.pi))

    def phase_step_error(self, frame: FrameSpec) -> float:
        """This frame's error (rad) on its nominal phase step, N(0, σ) (0 if ideal).

        Drawn per azimuth, polar angle, period and step, the same for the object and the
        reference: a projector's stepping error repeats, so the phase constant that the
        reference frames measure stays the object's (SCAN_BUNDLE.md) and what is left is a
        ripple of the 4-step phase.
        """
        sigma = self.physics.phase_step_error_deg
        if sigma == 0:
            return 0.0
        keys = _key(frame.azimuth_deg % 360, frame.polar_deg, frame.period_um, frame.phase_deg)
        rng = np.random.default_rng([self.seed, 0x57E9, *keys])
        return float(np.radians(rng.normal(0.0, sigma)))

    def modulation_scale(
        self, azimuth_deg: float, polar_deg: float, x_um: np.ndarray, y_um: np.ndarray
    ) -> np.ndarray | float:
        """Factor in [1 - spread, 1]·[1 - variation, 1] on the modulation, per azimuth and
        across the field (a smooth quadratic in the field coordinates of p')."""
        spread = self.physics.modulation_azimuth_spread
        variation = self.physics.modulation_field_variation
        if spread == 0 and variation == 0:
            return 1.0
        rng = np.random.default_rng([self.seed, 0x30D, *_key(azimuth_deg % 360, polar_deg)])
        az = 1.0 - spread * rng.uniform()
        c = rng.uniform(-1, 1, 5)
        xn = (x_um - self.field_width_um / 2) / (self.field_width_um / 2)
        yn = (y_um - self.field_height_um / 2) / (self.field_height_um / 2)
        poly = c[0] * xn + c[1] * yn + c[2] * xn * xn + c[3] * yn * yn + c[4] * xn * yn
        poly = np.clip(poly / np.sum(np.abs(c)), -1.0, 1.0)  # in [-1, 1] inside the field
        return (az * (1.0 - variation * (0.5 + 0.5 * poly))).astype(np.float32)

    def hot_e(self, shape: tuple[int, int], noise: NoiseModel) -> np.ndarray | None:
        """Dark current (H, W) electrons per unit exposure of the hot pixels, or None.

        A hot pixel leaks 5 % to 100 % of the full well per unit exposure; the dark frames
        carry it too, so it cancels where it does not saturate.
        """
        fraction = self.physics.hot_pixel_fraction
        if fraction == 0:
            return None
        key = ("hot", shape, noise.full_well_e, fraction)
        if key not in self._offsets:
            rng = np.random.default_rng([self.seed, 0x407])
            hot = rng.uniform(size=shape) < fraction
            rate = rng.uniform(0.05, 1.0, shape) * noise.full_well_e
            self._offsets[key] = np.where(hot, rate, 0.0)
        return self._offsets[key]

    def offset_e(self, shape: tuple[int, int], noise: NoiseModel) -> np.ndarray:
        """The camera's dark offset + fixed pattern (H, W) electrons, the same for every frame."""
        key = (shape, noise)
        if key not in self._offsets:
            self._offsets[key] = fixed_pattern_e(shape, noise, self.seed)
        return self._offsets[key]


def _specular(view: View, light: np.ndarray, ndotl: np.ndarray, lobes) -> np.ndarray:
    """Σ k_s·max(0, n·ĥ)^α over Blinn-Phong lobes (k_s, α), ĥ the half vector between the
    light and the telecentric view direction (0, 0, -1); on the tablet, where it is lit."""
    half = light + np.array([0, 0, -1], np.float32)
    half /= np.linalg.norm(half)
    ndoth = np.maximum(view.normals_ss @ half, 0)
    out = np.zeros(ndotl.shape, np.float32)
    for weight, exponent in lobes:
        out += np.float32(weight) * ndoth ** np.float32(exponent)
    return out * (ndotl > 0) * view.tablet_ss


def _shading(view: View, frame: FrameSpec, rig: Rig, noise: NoiseModel, *, split: bool = False):
    """E(p')·V·(ρ·max(0, n·l) + specular) and the fringe argument 2π(u·p') per sample.

    With ``split`` a dict instead: ``diffuse`` and ``specular`` (the two terms apart, the
    specular one None if there is none), ``arg``, and p' as ``px``, ``py``.
    """
    phi, theta = np.radians(frame.azimuth_deg), np.radians(frame.polar_deg)
    ux, uy = np.sin(phi), np.cos(phi)
    light = np.array([np.sin(theta) * ux, np.sin(theta) * uy, -np.cos(theta)], np.float32)
    # float32 throughout: coordinates <= 1e5 µm keep 0.01 µm precision, phases 1e-4 rad.
    xs = sample_coords_um(view.width, view.pixel_size_um, view.supersample)[None, :]
    ys = sample_coords_um(view.height, view.pixel_size_um, view.supersample)[:, None]
    xs, ys = xs.astype(np.float32), ys.astype(np.float32)
    source = "projector" if frame.kind == "fringe" else "lamp"
    if frame.target == "reference":
        shape = (ys.shape[0], xs.shape[1])
        px, py = np.broadcast_to(xs, shape), np.broadcast_to(ys, shape)
        diffuse = rig.reflectance_reference * np.cos(theta)
        irr = rig.irradiance(source, frame.azimuth_deg, frame.polar_deg, px, py)
        base = (irr * diffuse).astype(np.float32)
        spec = None
    else:
        h = view.height_ss_um
        shift = h * np.float32(np.tan(theta))
        px, py = xs - shift * np.float32(ux), ys - shift * np.float32(uy)
        ndotl = view.normals_ss @ light
        if frame.kind == "color":
            rho = view.albedo_ss[..., CHANNELS.index(frame.channel)]
        else:
            if "grey" not in view.cache:
                view.cache["grey"] = view.albedo_ss.mean(axis=-1)
            rho = view.cache["grey"]
        shade = rho * np.maximum(ndotl, 0)
        spec = None
        if noise.specular_weight > 0:
            half = light + np.array([0, 0, -1], np.float32)
            half /= np.linalg.norm(half)
            lobe = np.maximum(view.normals_ss @ half, 0) ** np.float32(noise.specular_exponent)
            spec = np.float32(noise.specular_weight) * lobe * (ndotl > 0) * view.tablet_ss
        if rig.physics.specular_lobes:
            extra = _specular(view, light, ndotl, rig.physics.specular_lobes)
            spec = extra if spec is None else spec + extra
        if spec is not None and not split:
            shade += spec
        key = ("shadow", round(frame.azimuth_deg % 360, 6), round(frame.polar_deg, 6))
        if key not in view.cache:
            view.cache[key] = cast_shadow(
                h, view.sample_step_um, frame.azimuth_deg, frame.polar_deg
            )
        irr = rig.irradiance(source, frame.azimuth_deg, frame.polar_deg, px, py)
        base = (irr * shade * view.cache[key]).astype(np.float32)
        if split and spec is not None:
            spec = (irr * spec * view.cache[key]).astype(np.float32)
    gain = np.float32(rig.source_radiance)
    if frame.kind == "color":
        base *= np.float32(rig.channel_gain[CHANNELS.index(frame.channel)])
        if split and spec is not None:
            spec *= np.float32(rig.channel_gain[CHANNELS.index(frame.channel)])
    arg = None
    if frame.kind == "fringe":
        arg = (np.float32(2 * np.pi) * (px * np.float32(ux) + py * np.float32(uy))).astype(
            np.float32
        )
    if split:
        return {
            "diffuse": base * gain,
            "specular": None if spec is None else spec * gain,
            "arg": arg,
            "px": px,
            "py": py,
        }
    return base * gain, arg


def _cached(view: View, slot: str, key: tuple, make):
    """view.cache keeps one entry per slot: frames come grouped, so the last one is reused."""
    entry = view.cache.get(slot)
    if entry is None or entry[0] != key:
        view.cache[slot] = entry = (key, make())
    return entry[1]


def _fringe_terms(view: View, frame: FrameSpec, rig: Rig, noise: NoiseModel):
    """Pixel box means of b, b·cos(a/P), b·sin(a/P) (b the shading, a the fringe argument).

    box(b·(1 + m·cos(a/P + δ))) = B + m·(cos δ·C - sin δ·S), so the four phase steps of a
    fringe set cost one supersampled evaluation.
    """
    light_key = (frame.target, round(frame.azimuth_deg % 360, 6), round(frame.polar_deg, 6))
    base, arg = _cached(
        view, "fringe_shading", light_key, lambda: _shading(view, frame, rig, noise)
    )

    def terms():
        phase = arg / np.float32(frame.period_um)
        ss = view.supersample
        return (
            box_mean(base, ss).astype(np.float64),
            box_mean(base * np.cos(phase), ss).astype(np.float64),
            box_mean(base * np.sin(phase), ss).astype(np.float64),
        )

    return _cached(view, "fringe_terms", (*light_key, round(frame.period_um, 6)), terms)


def _needs_general_fringes(physics: Physics) -> bool:
    """Whether fringe frames need the per-frame path (the ideal one decomposes into 3 terms)."""
    return not (
        physics.projector_is_sinusoid
        and physics.projector_defocus_um == 0
        and physics.phase_step_error_deg == 0
        and physics.modulation_azimuth_spread == 0
        and physics.modulation_field_variation == 0
        and physics.subsurface_um == 0
    )


def _scatter_in_clay(view: View, factor: np.ndarray, physics: Physics) -> np.ndarray:
    """(1 - f)·F + f·(G_σ * F) on the tablet: light of the pattern F that enters the clay
    leaves it spread by a Gaussian of σ = subsurface_um (a normalised convolution inside
    the tablet, so the background does not bleed in); F unchanged off the tablet."""
    sigma = physics.subsurface_um / view.sample_step_um
    inside = view.tablet_ss.astype(np.float32)
    weight = _cached(view, "clay_weight", (sigma,), lambda: gaussian_filter(inside, sigma))
    blurred = gaussian_filter(factor * inside, sigma) / np.maximum(weight, np.float32(1e-6))
    f = np.float32(physics.subsurface_fraction)
    return np.where(view.tablet_ss, (1 - f) * factor + f * blurred, factor).astype(np.float32)


def _fringe_general(view: View, frame: FrameSpec, rig: Rig, noise: NoiseModel) -> np.ndarray:
    """Pixel radiance (H, W) of a fringe frame with the projector and clay of ``rig.physics``.

    L = E(p')·V·[ρ·max(0, n·l)·F_clay + specular·F] with F = 1 + A(p')·(F_proj(u·p') - 1),
    F_proj the projector's profile (projector.py) at the frame's phase plus its step error,
    A the modulation's azimuth and field factor, F_clay the pattern after scattering in the
    clay (object frames only).
    """
    physics = rig.physics
    light_key = (frame.target, round(frame.azimuth_deg % 360, 6), round(frame.polar_deg, 6))
    parts = _cached(
        view, "fringe_parts", light_key, lambda: _shading(view, frame, rig, noise, split=True)
    )
    delta = (
        np.radians(frame.phase_deg)
        + rig.phase_offset(frame.azimuth_deg, frame.polar_deg, frame.period_um)
        + rig.phase_step_error(frame)
    )
    profile = fringe_profile(
        parts["arg"].astype(np.float64) / (2 * np.pi),
        period_um=frame.period_um,
        phase_rad=float(delta),
        modulation=noise.fringe_modulation,
        defocus_um=physics.projector_defocus_um,
        pixel_um=physics.projector_pixel_um,
        levels=physics.projector_levels,
        gamma=physics.projector_gamma,
    )
    scale = rig.modulation_scale(frame.azimuth_deg, frame.polar_deg, parts["px"], parts["py"])
    factor = (1 + scale * (profile - 1)).astype(np.float32)
    diffuse_factor = factor
    if physics.subsurface_um > 0 and frame.target == "object":
        diffuse_factor = _scatter_in_clay(view, factor, physics)
    samples = parts["diffuse"] * diffuse_factor
    if parts["specular"] is not None:
        samples += parts["specular"] * factor
    return box_mean(samples, view.supersample).astype(np.float64)


def _lowpass(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of σ px; wide ones on a k× coarser grid (k = σ/4: block means, a
    Gaussian of the remaining σ, bilinear back), which is as smooth and 10-50× cheaper."""
    k = int(sigma_px // 4)
    if k < 2:
        return gaussian_filter(image, sigma_px, mode="nearest")
    h, w = image.shape
    padded = np.pad(image, ((0, -h % k), (0, -w % k)), mode="edge")
    small = padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k).mean(axis=(1, 3))
    # A k-pixel box has variance (k² - 1)/12 px²; the Gaussian adds the rest.
    rest = np.sqrt(max(sigma_px**2 - (k * k - 1) / 12, 0.0)) / k
    small = gaussian_filter(small, rest, mode="nearest")
    rows = (np.arange(h) + 0.5) / k - 0.5
    cols = (np.arange(w) + 0.5) / k - 0.5
    coords = np.meshgrid(rows, cols, indexing="ij")
    return map_coordinates(small, coords, order=1, mode="nearest")


def _interreflection(view: View, radiance: np.ndarray, physics: Physics) -> np.ndarray:
    """Second bounce: f·ρ(p)·c(p)·(G_σ * L)(p), with c = clip((G_σ*h - h)/(σ/4), 0, 1) the
    concavity (how far p lies below its surroundings: a flat or convex surface sees none of
    itself, the floor of a wedge or chip does) and G_σ a Gaussian of σ = interreflection_um."""
    sigma_px = physics.interreflection_um / view.pixel_size_um

    def weight():
        h = box_mean(view.height_ss_um, view.supersample).astype(np.float64)
        below = _lowpass(h, sigma_px) - h
        concave = np.clip(below / (0.25 * physics.interreflection_um), 0.0, 1.0)
        rho = box_mean(view.albedo_ss, view.supersample).mean(axis=-1).astype(np.float64)
        return physics.interreflection * rho * concave

    w = _cached(view, "interreflection", (sigma_px, physics.interreflection), weight)
    return w * _lowpass(radiance, sigma_px)


def frame_radiance(view: View, frame: FrameSpec, rig: Rig, noise: NoiseModel) -> np.ndarray:
    """Radiance (H, W) float64 that reaches the sensor for ``frame`` (before exposure and noise).

    ``noise`` gets ``rig.physics``' camera overrides here (``Physics.camera``, idempotent).
    """
    physics = rig.physics
    noise = physics.camera(noise)
    if frame.kind == "dark":
        return np.zeros((view.height, view.width))
    if frame.kind == "fringe" and _needs_general_fringes(physics):
        radiance = _fringe_general(view, frame, rig, noise)
    elif frame.kind == "fringe":
        b, c, s = _fringe_terms(view, frame, rig, noise)
        delta = np.radians(frame.phase_deg) + rig.phase_offset(
            frame.azimuth_deg, frame.polar_deg, frame.period_um
        )
        radiance = b + noise.fringe_modulation * (np.cos(delta) * c - np.sin(delta) * s)
    else:
        samples, _ = _shading(view, frame, rig, noise)
        radiance = box_mean(samples, view.supersample).astype(np.float64)
    if physics.interreflection > 0 and frame.target == "object":
        radiance = radiance + _interreflection(view, radiance, physics)
    if physics.veil > 0:
        radiance = radiance + physics.veil * float(radiance.mean())
    radiance += noise.stray_light
    if noise.blur_sigma_px > 0:
        radiance = gaussian_filter(radiance, noise.blur_sigma_px, mode="nearest")
    return radiance


def render_frame(
    view: View,
    frame: FrameSpec,
    noise: NoiseModel,
    rng: np.random.Generator,
    *,
    rig: Rig | None = None,
) -> np.ndarray:
    """Stored values (H, W) uint16 of one frame: the simulated camera.

    ``rig`` defaults to the instrument of seed 0 with the view's field; pass the same Rig
    for every frame of a scan (its fixed pattern and source fields must not change).
    """
    if rig is None:
        rig = Rig(
            0,
            view.width * view.pixel_size_um,
            view.height * view.pixel_size_um,
            irradiance_variation=noise.irradiance_variation,
        )
    noise = rig.physics.camera(noise)
    radiance = frame_radiance(view, frame, rig, noise)
    shape = (view.height, view.width)
    offset = rig.offset_e(shape, noise)
    return encode_frame(
        radiance,
        noise=noise,
        exposure=frame.exposure,
        offset_e=offset,
        rng=rng,
        hot_e=rig.hot_e(shape, noise),
    )
