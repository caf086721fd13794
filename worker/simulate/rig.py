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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter

from worker.simulate.noise import NoiseModel, encode_frame, fixed_pattern_e
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

    def offset_e(self, shape: tuple[int, int], noise: NoiseModel) -> np.ndarray:
        """The camera's dark offset + fixed pattern (H, W) electrons, the same for every frame."""
        key = (shape, noise)
        if key not in self._offsets:
            self._offsets[key] = fixed_pattern_e(shape, noise, self.seed)
        return self._offsets[key]


def _shading(
    view: View, frame: FrameSpec, rig: Rig, noise: NoiseModel
) -> tuple[np.ndarray, np.ndarray]:
    """E(p')·V·(ρ·max(0, n·l) + specular) and the fringe argument 2π(u·p') per sample."""
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
        if noise.specular_weight > 0:
            half = light + np.array([0, 0, -1], np.float32)
            half /= np.linalg.norm(half)
            lobe = np.maximum(view.normals_ss @ half, 0) ** np.float32(noise.specular_exponent)
            shade += np.float32(noise.specular_weight) * lobe * (ndotl > 0) * view.tablet_ss
        key = ("shadow", round(frame.azimuth_deg % 360, 6), round(frame.polar_deg, 6))
        if key not in view.cache:
            view.cache[key] = cast_shadow(
                h, view.sample_step_um, frame.azimuth_deg, frame.polar_deg
            )
        irr = rig.irradiance(source, frame.azimuth_deg, frame.polar_deg, px, py)
        base = (irr * shade * view.cache[key]).astype(np.float32)
    if frame.kind == "color":
        base *= np.float32(rig.channel_gain[CHANNELS.index(frame.channel)])
    arg = None
    if frame.kind == "fringe":
        arg = (np.float32(2 * np.pi) * (px * np.float32(ux) + py * np.float32(uy))).astype(
            np.float32
        )
    return base * np.float32(rig.source_radiance), arg


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


def frame_radiance(view: View, frame: FrameSpec, rig: Rig, noise: NoiseModel) -> np.ndarray:
    """Radiance (H, W) float64 that reaches the sensor for ``frame`` (before exposure and noise)."""
    if frame.kind == "dark":
        return np.zeros((view.height, view.width))
    if frame.kind == "fringe":
        b, c, s = _fringe_terms(view, frame, rig, noise)
        delta = np.radians(frame.phase_deg) + rig.phase_offset(
            frame.azimuth_deg, frame.polar_deg, frame.period_um
        )
        radiance = b + noise.fringe_modulation * (np.cos(delta) * c - np.sin(delta) * s)
    else:
        samples, _ = _shading(view, frame, rig, noise)
        radiance = box_mean(samples, view.supersample).astype(np.float64)
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
    radiance = frame_radiance(view, frame, rig, noise)
    offset = rig.offset_e((view.height, view.width), noise)
    return encode_frame(radiance, noise=noise, exposure=frame.exposure, offset_e=offset, rng=rng)
