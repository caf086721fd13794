"""Camera and source imperfections: the noise presets and the sensor model.

The sensor turns radiance into stored values the way SCAN_BUNDLE.md reads them back:
``lin(v) = (v / (2^bit_depth - 1))^gamma`` and ``L = (lin(v) - lin(v_dark)) / exposure``.
Radiance is simulated in units of the linear full scale at exposure 1, so a
conforming reader recovers the simulated radiance (up to noise).

Sensor chain for one frame (all per pixel):

1. signal electrons ``s = L * exposure * full_well_e`` (+ dark current * exposure);
2. shot noise: ``s ~ Poisson(s)``;
3. bias offset + fixed-pattern noise (the same in every frame) + Gaussian read noise;
4. clip to the full well, normalise by it, apply the response ``lin^(1/gamma)``;
5. quantise to ``bit_depth`` bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["NOISE_PRESETS", "NoiseModel", "encode_frame", "fixed_pattern_e", "noise_model"]


@dataclass(frozen=True)
class NoiseModel:
    """Everything about the instrument that is not the ideal model of the spec.

    Tests derive their tolerances from these numbers (see ``dn_step_radiance``).
    """

    name: str
    bit_depth: int = 12
    response_gamma: float = 1.0
    full_well_e: float = 20_000.0
    read_noise_e: float = 10.0
    shot_noise: bool = True
    dark_offset_e: float = 200.0  # bias, in electron equivalents
    fixed_pattern_e: float = 20.0  # sigma of the per-pixel offset pattern
    dark_current_e: float = 10.0  # per unit exposure
    fringe_modulation: float = 0.85  # m of the spec, 0 < m <= 1
    specular_weight: float = 0.05  # Blinn-Phong lobe weight relative to a white diffuser
    specular_exponent: float = 40.0
    stray_light: float = 0.0  # additive radiance in lit frames (not in darks)
    blur_sigma_px: float = 0.5  # camera point-spread function (Gaussian)
    irradiance_variation: float = 0.15  # +- relative non-uniformity of E(p)
    exposures: tuple[float, ...] = (1.0,)  # exposures used, chosen per frame

    def __post_init__(self) -> None:
        if not 8 <= self.bit_depth <= 16:
            raise ValueError(f"bit_depth must be 8..16, got {self.bit_depth}")
        if self.response_gamma <= 0:
            raise ValueError(f"response_gamma must be > 0, got {self.response_gamma}")
        if not 0 < self.fringe_modulation <= 1:
            raise ValueError(f"fringe_modulation must be in (0, 1], got {self.fringe_modulation}")
        if self.full_well_e <= 0:
            raise ValueError(f"full_well_e must be > 0, got {self.full_well_e}")
        if not self.exposures or min(self.exposures) <= 0:
            raise ValueError(f"exposures must be positive, got {self.exposures}")

    @property
    def max_value(self) -> int:
        """Largest stored value, 2^bit_depth - 1."""
        return (1 << self.bit_depth) - 1

    def dn_step_radiance(self, radiance: float, exposure: float = 1.0) -> float:
        """Radiance change of one stored step at ``radiance`` (linear units, exposure applied).

        With response ``lin = (v/M)^gamma`` one step of v changes lin by
        ``gamma * lin^((gamma-1)/gamma) / M``; divide by the exposure for radiance.
        """
        lin = max(radiance * exposure, 1e-12)
        return (
            self.response_gamma
            * lin ** ((self.response_gamma - 1) / self.response_gamma)
            / (self.max_value * exposure)
        )

    def radiance_sigma(self, radiance: float, exposure: float = 1.0) -> float:
        """Standard deviation of the radiance read back from one frame (dark subtracted once).

        Shot noise sqrt(s) electrons, read noise twice (frame and dark), quantisation
        (1/sqrt(12) step) twice; fixed pattern cancels in the dark subtraction.
        """
        signal_e = radiance * exposure * self.full_well_e
        var_e = (signal_e if self.shot_noise else 0.0) + 2 * self.read_noise_e**2
        var_q = 2 * self.dn_step_radiance(radiance, exposure) ** 2 / 12
        return float(np.sqrt(var_e / (exposure * self.full_well_e) ** 2 + var_q))


NOISE_PRESETS: dict[str, NoiseModel] = {
    "clean": NoiseModel(
        name="clean",
        bit_depth=16,
        read_noise_e=0.0,
        shot_noise=False,
        dark_offset_e=0.0,
        fixed_pattern_e=0.0,
        dark_current_e=0.0,
        fringe_modulation=0.9,
        specular_weight=0.0,
        blur_sigma_px=0.0,
    ),
    "default": NoiseModel(name="default"),
    "hard": NoiseModel(
        name="hard",
        bit_depth=12,
        response_gamma=2.2,
        full_well_e=10_000.0,
        read_noise_e=20.0,
        dark_offset_e=150.0,
        fixed_pattern_e=30.0,
        dark_current_e=40.0,
        fringe_modulation=0.7,
        specular_weight=0.25,
        specular_exponent=20.0,
        stray_light=0.01,
        blur_sigma_px=0.8,
        irradiance_variation=0.2,
        exposures=(0.5, 1.0, 2.0),
    ),
}


def noise_model(name: str) -> NoiseModel:
    """The preset called ``name`` (``clean``, ``default``, ``hard``)."""
    try:
        return NOISE_PRESETS[name]
    except KeyError:
        raise ValueError(
            f"noise: unknown preset {name!r}; choose from {sorted(NOISE_PRESETS)}"
        ) from None


def fixed_pattern_e(shape: tuple[int, int], noise: NoiseModel, seed: int) -> np.ndarray:
    """Per-pixel offset in electrons: bias + row/column banding + pixel pattern, (H, W) float64.

    Deterministic in ``seed`` so that every frame of a camera carries the same pattern.
    """
    if noise.fixed_pattern_e == 0 and noise.dark_offset_e == 0:
        return np.zeros(shape)
    rng = np.random.default_rng([seed, 0xF1ED])
    pixel = rng.normal(0.0, noise.fixed_pattern_e, shape)
    columns = rng.normal(0.0, 0.5 * noise.fixed_pattern_e, (1, shape[1]))
    return noise.dark_offset_e + pixel + columns


def encode_frame(
    radiance: np.ndarray,
    *,
    noise: NoiseModel,
    exposure: float,
    offset_e: np.ndarray,
    rng: np.random.Generator,
    hot_e: np.ndarray | None = None,
) -> np.ndarray:
    """Stored values of one frame, (H, W) uint16 in 0 .. 2^bit_depth - 1.

    ``radiance`` (H, W) is linear, in units of the full scale at exposure 1 (zeros for a
    dark frame); ``offset_e`` (H, W) is ``fixed_pattern_e``; ``rng`` draws shot and read noise;
    ``hot_e`` (H, W), if given, is the extra dark current of hot pixels per unit exposure.
    """
    if exposure <= 0:
        raise ValueError(f"exposure must be > 0, got {exposure}")
    radiance = np.asarray(radiance, dtype=np.float64)
    if radiance.ndim != 2 or offset_e.shape != radiance.shape:
        raise ValueError(
            f"radiance {radiance.shape} and offset_e {offset_e.shape} must match (H, W)"
        )
    signal_e = np.clip(radiance, 0.0, None) * (exposure * noise.full_well_e)
    signal_e += noise.dark_current_e * exposure
    if hot_e is not None:
        signal_e += hot_e * exposure
    if noise.shot_noise:
        # Beyond ~4 full wells the Poisson draw is pointless (clipped anyway) and slow.
        signal_e = rng.poisson(np.minimum(signal_e, 4 * noise.full_well_e)).astype(np.float64)
    total_e = signal_e + offset_e
    if noise.read_noise_e > 0:
        total_e += rng.normal(0.0, noise.read_noise_e, radiance.shape)
    lin = np.clip(total_e / noise.full_well_e, 0.0, 1.0)
    if noise.response_gamma != 1.0:
        lin = lin ** (1.0 / noise.response_gamma)
    return np.rint(lin * noise.max_value).astype(np.uint16)
