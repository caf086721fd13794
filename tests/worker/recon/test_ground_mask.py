"""The dark-ground mask (worker.recon.ground_mask): objects photographed on black velvet."""

import numpy as np
import pytest

from worker.recon.ground_mask import ground_mask, stack_peak
from worker.recon.photometric import light_directions


def _stack(
    rng,
    *,
    albedo=0.05,
    ground=0.02,
    size=96,
    radius=30.0,
    vignetting=0.0,
    k=24,
    lobe=0.5,
    noise=0.002,
):
    """A hemisphere of reflectance `albedo` with a glossy lobe on a flat ground, under k
    lights, with pixel-area coverage at the rim, shot-like noise, a fall-off of the light
    toward the corners and a few hot pixels. Returns the stack and the true (centre) mask."""
    ss = 4  # supersamples per pixel side for the rim's coverage
    g = (np.arange(size * ss) + 0.5) / ss - 0.5
    x, y = np.meshgrid(g - size / 2, g - size / 2)
    r2 = x * x + y * y
    inside = r2 < radius**2
    nz = -np.sqrt(np.clip(1 - r2 / radius**2, 0, 1))
    n = np.stack([x / radius, y / radius, nz], -1)
    n[~inside] = (0, 0, -1)
    lights = light_directions(np.arange(k) * 360 / k, np.linspace(10, 50, k))
    half = lights + (0, 0, -1)
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    cos = np.clip(np.einsum("hwc,kc->khw", n, lights), 0, None)
    spec = np.clip(np.einsum("hwc,kc->khw", n, half), 0, 1) ** 60 * (cos > 0)
    rho = np.where(inside, albedo, ground)
    s = rho * cos + np.where(inside, lobe, 0.0) * spec
    s = s.reshape(k, size, ss, size, ss).mean(axis=(2, 4))
    yy, xx = np.mgrid[0:size, 0:size] - size / 2
    s *= 1 - vignetting * (xx**2 + yy**2) / (size / 2) ** 2
    s = s + rng.normal(size=s.shape) * noise * np.sqrt(s / 0.05 + 0.1)
    hot = rng.integers(0, size, (2, 6))
    s[:, hot[0], hot[1]] += 0.5
    c = np.arange(size) - size / 2
    truth = (c[None, :] ** 2 + c[:, None] ** 2) < radius**2
    return s.astype(np.float32), truth


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


def test_stack_peak_ignores_one_bright_sample():
    s = np.zeros((30, 4, 4), np.float32)
    s[:, 0, 0] = np.arange(30)
    s[5, 1, 1] = 100.0  # one hot sample
    s[:, 2, 2] = np.nan
    peak = stack_peak(s)
    assert peak[1, 1] == 0.0
    assert 26 <= peak[0, 0] < 29
    assert np.isnan(peak[2, 2])
    with pytest.raises(ValueError, match="stack"):
        stack_peak(np.ones((4, 4)))


@pytest.mark.parametrize("albedo", [0.05, 0.4])
def test_dark_and_light_objects_on_velvet_are_found_whole(albedo):
    rng = np.random.default_rng(0)
    s, truth = _stack(rng, albedo=albedo, vignetting=0.3)
    found = ground_mask(stack_peak(s))
    assert found.stood_down is None
    assert _iou(found.mask, truth) > 0.97
    # Hot pixels on the ground and the brighter centre of the ground are not object.
    assert not found.mask[:8].any() and not found.mask[:, :8].any()
    assert found.ground_level == pytest.approx(0.02 * np.cos(np.radians(30)), rel=0.5)


def test_noiseless_renders_keep_the_ground_out():
    """No noise to set the floor by (a renderer's output): the ground's own shading under
    the vignetting is not taken for object."""
    rng = np.random.default_rng(5)
    s, truth = _stack(rng, noise=0.0, vignetting=0.3)
    found = ground_mask(stack_peak(s))
    assert found.stood_down is None
    assert _iou(found.mask, truth) > 0.97


def test_no_dark_ground_stands_down_to_every_measured_pixel():
    rng = np.random.default_rng(1)
    # A matte ball on a ground as light as itself: its top reads as the ground does.
    s, _ = _stack(rng, albedo=0.4, ground=0.4, lobe=0.0)
    has_normal = np.ones(s.shape[1:], bool)
    has_normal[0, 0] = False
    found = ground_mask(stack_peak(s), has_normal=has_normal)
    assert found.stood_down is not None
    assert found.mask.sum() == has_normal.sum()


def test_an_object_filling_the_frame_stands_down():
    rng = np.random.default_rng(2)
    s, _ = _stack(rng, albedo=0.4, radius=300.0)  # a dome filling the frame
    found = ground_mask(stack_peak(s))
    assert found.stood_down is not None
    assert found.mask.all()


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match="peak"):
        ground_mask(np.ones(5))
    with pytest.raises(ValueError, match="has_normal"):
        ground_mask(np.ones((8, 8)), has_normal=np.ones((4, 4), bool))
