"""The sensor model: read-back statistics match the declared noise parameters."""

from __future__ import annotations

import numpy as np
import pytest

from worker.simulate.noise import (
    NOISE_PRESETS,
    NoiseModel,
    encode_frame,
    fixed_pattern_e,
    noise_model,
)


def _lin(v: np.ndarray, noise: NoiseModel) -> np.ndarray:
    return (v.astype(np.float64) / noise.max_value) ** noise.response_gamma


@pytest.mark.parametrize("name", ["default", "hard"])
def test_read_back_radiance_has_declared_mean_and_sigma(name):
    noise = noise_model(name)
    shape = (128, 128)
    offset = fixed_pattern_e(shape, noise, seed=3)
    radiance, exposure = 0.3, 1.0
    rng = np.random.default_rng(0)
    frame = encode_frame(
        np.full(shape, radiance), noise=noise, exposure=exposure, offset_e=offset, rng=rng
    )
    dark = encode_frame(np.zeros(shape), noise=noise, exposure=exposure, offset_e=offset, rng=rng)
    read = (_lin(frame, noise) - _lin(dark, noise)) / exposure
    sigma = noise.radiance_sigma(radiance, exposure)
    n = read.size
    # Mean within 5 standard errors; the sample sigma within 5 of its standard errors
    # (relative 1/sqrt(2n)) plus 10 % for the gamma's non-linearity on the dark level.
    assert abs(read.mean() - radiance) < 5 * sigma / np.sqrt(n) + 2 * noise.dn_step_radiance(
        radiance
    )
    assert read.std() == pytest.approx(sigma, rel=5 / np.sqrt(2 * n) + 0.1)


def test_values_stay_within_bit_depth_and_clip():
    noise = noise_model("default")
    shape = (8, 8)
    v = encode_frame(
        np.full(shape, 5.0),
        noise=noise,
        exposure=2.0,
        offset_e=fixed_pattern_e(shape, noise, 1),
        rng=np.random.default_rng(1),
    )
    assert v.dtype == np.uint16 and v.max() == noise.max_value


def test_clean_is_quantisation_only():
    noise = NOISE_PRESETS["clean"]
    shape = (16, 16)
    ramp = np.linspace(0, 0.9, 256).reshape(shape)
    v = encode_frame(
        ramp,
        noise=noise,
        exposure=1.0,
        offset_e=fixed_pattern_e(shape, noise, 0),
        rng=np.random.default_rng(0),
    )
    assert np.max(np.abs(v / noise.max_value - ramp)) <= 0.5 / noise.max_value + 1e-12


def test_fixed_pattern_is_the_same_in_every_frame():
    noise = noise_model("default")
    a, b = fixed_pattern_e((10, 12), noise, 5), fixed_pattern_e((10, 12), noise, 5)
    assert np.array_equal(a, b) and a.std() > 0


def test_bad_presets_and_parameters_are_refused():
    with pytest.raises(ValueError, match="noise"):
        noise_model("loud")
    with pytest.raises(ValueError, match="bit_depth"):
        NoiseModel(name="x", bit_depth=20)
    with pytest.raises(ValueError, match="fringe_modulation"):
        NoiseModel(name="x", fringe_modulation=0.0)
