import numpy as np
import pytest

from worker.recon.color import grey_reflectance, linear_to_srgb8, rgb_reflectance
from worker.recon.photometric import light_directions
from worker.recon.radiometry import flat_field


def test_rgb_reflectance_recovers_colour_despite_shadows_and_highlights(
    recon_sphere, recon_sense, recon_sigma
):
    rng = np.random.default_rng(6)
    scene = recon_sphere(48, radius_px=30.0)
    h, w = scene.height_um.shape
    rgb_true = rng.uniform(0.1, 0.8, (h, w, 3))
    az = np.arange(6) * 60.0
    channels = [c for c in ("red", "green", "blue") for _ in az]
    ls = light_directions(np.tile(az, 3), 45.0)
    cos = np.einsum("hwc,kc->khw", scene.normals, ls)
    rho = np.stack([rgb_true[..., i] for i in range(3) for _ in az])
    l_obj = 0.9 * rho * np.clip(cos, 0, None)
    # One cast shadow and one highlight on some frames of some pixels.
    corrupt = rng.uniform(size=l_obj.shape)
    l_obj = np.where(corrupt < 0.05, 0.0, l_obj)
    l_obj = np.where((corrupt > 0.95) & (cos > 0), l_obj + 0.4, l_obj)
    l_ref = 0.9 * np.cos(np.deg2rad(45.0)) * np.ones_like(l_obj)
    s = flat_field(
        recon_sense(l_obj, rng), recon_sense(l_ref, rng), reference_reflectance=1.0, polar_deg=45.0
    )
    res = rgb_reflectance(s, channels, ls, scene.normals)
    est = res.rgb
    # Judged where every channel has at least as many clean samples (n·l ≥ min_cos = 0.3,
    # not corrupted) as corrupted ones: there the lower median is a clean sample.
    usable = cos >= 0.3
    bad = usable & ((corrupt < 0.05) | (corrupt > 0.95))
    clean = usable & ~bad
    per_c = lambda m: np.stack([m[i * 6 : (i + 1) * 6].sum(axis=0) for i in range(3)], -1)  # noqa: E731
    ok = np.all((per_c(clean) >= 1) & (per_c(clean) >= per_c(bad)), axis=-1)
    assert np.mean(ok) > 0.9
    # Per sample σ_ρ = σ_s/(n·l); σ_s ≤ sqrt(2)·σ(0.9)/0.9 (object and reference terms at
    # full signal) and n·l ≥ 0.3 give σ_ρ ≤ 0.035 for one sample; the mean of the kept
    # samples is better.  6σ of one sample at the worst cosine bounds every pixel, and the
    # median error stays below one such σ.
    sig_worst = np.sqrt(recon_sigma(0.9) ** 2 * 2) / 0.9 / 0.3
    assert np.all(np.abs(est[ok] - rgb_true[ok]) < 6 * sig_worst)
    assert np.median(np.abs(est[ok] - rgb_true[ok])) < sig_worst
    assert np.all(res.samples_used[ok] >= 1)


def test_rgb_reflectance_grey_fallback():
    s = np.full((3, 2, 2), np.nan, dtype=np.float32)
    ls = light_directions([0.0, 120.0, 240.0], 40.0)
    normals = np.zeros((2, 2, 3))
    normals[..., 2] = -1
    albedo = np.array([[0.2, 0.4], [0.6, np.nan]])
    res = rgb_reflectance(s, ["red", "green", "blue"], ls, normals, fallback_albedo=albedo)
    np.testing.assert_allclose(res.rgb[0, 1], [0.4, 0.4, 0.4], rtol=1e-6)
    assert res.fallback[0, 1] and not res.fallback[1, 1]
    assert np.all(np.isnan(res.rgb[1, 1]))
    np.testing.assert_allclose(grey_reflectance(albedo)[1, 0], [0.6] * 3, rtol=1e-6)


def test_linear_to_srgb8_reference_values():
    # IEC 61966-2-1: 0.18 → 0.4614 (118), 0.5 → 0.7354 (188), 0.0031308 → 0.04045 (10).
    x = np.array([0.0, 0.0031308, 0.18, 0.5, 1.0, 2.0, -1.0, np.nan])
    np.testing.assert_array_equal(linear_to_srgb8(x), [0, 10, 118, 188, 255, 255, 0, 0])
    assert linear_to_srgb8(np.zeros((2, 2, 3))).dtype == np.uint8


def test_rgb_reflectance_rejects_bad_channel():
    ls = light_directions([0.0, 120.0], 40.0)
    with pytest.raises(ValueError, match="channel"):
        rgb_reflectance(np.ones((2, 2, 2)), ["red", "purple"], ls, np.zeros((2, 2, 3)))


@pytest.mark.slow
@pytest.mark.xdist_group("recon_sim")
def test_simulated_bundle_colour_against_ground_truth(simulated_recon):
    r = simulated_recon
    e = np.abs(r.rgb[r.smooth] - r.gt_albedo[r.smooth])
    # One sample: σ_ρ = ρ·σ_s/s ≈ 0.4 × 1.6 % ≈ 0.007 (the photometric fit residual of this
    # scan); 2–4 samples averaged give ≈ 0.004, median |error| ≈ 0.003.  A 1° normal error
    # at n·l ≈ 0.7 adds ≈ 2.5 % of ρ ≈ 0.01.  0.02 catches a wrong channel or reference.
    assert np.all(np.nanmedian(e, axis=0) < 0.02)
    assert np.mean(np.isfinite(r.rgb[r.mask])) > 0.99


def test_rgb_reflectance_does_not_depend_on_the_pixel_blocks(monkeypatch):
    # Pixels are independent: blocks of any size (here 7 px, the last one partial) give
    # the very same bits as one block, shadows, highlights and unusable samples included.
    import worker.recon.color as color

    rng = np.random.default_rng(9)
    h, w = 9, 11
    ls = light_directions(np.tile(np.arange(4) * 90.0 + 20.0, 3), 45.0)
    normals = rng.normal(size=(h, w, 3)) * [0.3, 0.3, 1.0]
    normals[..., 2] = -np.abs(normals[..., 2])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    cos = np.einsum("hwc,kc->khw", normals, ls)
    s = (rng.uniform(0.1, 0.8, (12, h, w)) * np.clip(cos, 0, None)).astype(np.float32)
    s[rng.uniform(size=s.shape) < 0.1] += 0.5
    s[rng.uniform(size=s.shape) < 0.05] = np.nan
    s[:4, 2, 3] = np.nan  # no red sample at all there
    channels = [c for c in ("red", "green", "blue") for _ in range(4)]
    whole = rgb_reflectance(s, channels, ls, normals)
    monkeypatch.setattr(color, "_BLOCK_PIXELS", 7)
    blocks = rgb_reflectance(s, channels, ls, normals)
    np.testing.assert_array_equal(blocks.rgb.view(np.int32), whole.rgb.view(np.int32))
    np.testing.assert_array_equal(blocks.samples_used, whole.samples_used)
    assert np.any(whole.samples_used > 0) and np.any(np.isnan(whole.rgb))


def test_linear_to_srgb8_float32_table_matches_the_formula():
    # The float32 path encodes by table: the very codes of the float64 formula, around
    # every code boundary, on random patterns of [0, 1] and on the values it clips.
    def formula(x):
        x = np.clip(np.nan_to_num(np.float64(x), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
        v = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
        return np.round(255.0 * v).astype(np.uint8)

    rng = np.random.default_rng(10)
    one = int(np.float32(1.0).view(np.int32))
    bits = rng.integers(0, one + 1, 200_000)
    # Each code's first float32 and its neighbours (found from the formula, not the table).
    grid = np.arange(0, one + 1, 4096)
    first = grid[np.flatnonzero(np.diff(formula(grid.astype(np.int32).view(np.float32))))]
    near = (first[:, None] + np.arange(-4096, 4097, 64)).clip(0, one).ravel()
    x = np.concatenate([bits, near]).astype(np.int32).view(np.float32)
    specials = np.array([np.nan, -np.nan, np.inf, -np.inf, -0.0, -1.0, 1.5, 1e30, 1e-45])
    x = np.concatenate([specials.astype(np.float32), x])
    x = x[: x.size // 3 * 3].reshape(-1, 3)
    got = linear_to_srgb8(x)
    assert got.dtype == np.uint8 and got.shape == x.shape
    np.testing.assert_array_equal(got, formula(x))
    np.testing.assert_array_equal(got, linear_to_srgb8(x.astype(np.float64)))
