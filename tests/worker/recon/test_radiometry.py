import numpy as np
import pytest

from worker.recon.radiometry import flat_field


def test_flat_field_recovers_shading_under_nonuniform_irradiance(recon_sense, recon_sigma):
    rng = np.random.default_rng(1)
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    # A lamp footprint falling to 40 % at the corners: the division must cancel it.
    irradiance = 0.4 + 0.6 * np.exp(-((xx - 30) ** 2 + (yy - 20) ** 2) / (2 * 30.0**2))
    rho = rng.uniform(0.2, 0.9, (h, w))
    theta = 40.0
    cos_nl = rng.uniform(0.3, 1.0, (h, w))  # n·l of each pixel
    gain, rho_ref = 0.9, 0.95
    l_obj = gain * irradiance * rho * cos_nl
    l_ref = gain * irradiance * rho_ref * np.cos(np.deg2rad(theta))
    obj, ref = recon_sense(l_obj, rng), recon_sense(l_ref, rng)
    obj_before, ref_before = obj.copy(), ref.copy()
    s = flat_field(obj, ref, reference_reflectance=rho_ref, polar_deg=theta)
    assert s.dtype == np.float32 and s.shape == (h, w)
    np.testing.assert_array_equal(obj, obj_before)
    np.testing.assert_array_equal(ref, ref_before)
    truth = rho * cos_nl
    # Ratio noise: σ_s / s = sqrt((σ_o/L_o)² + (σ_r/L_r)²); 3,072 pixels, so a 5.5σ bound
    # is exceeded by chance with probability ~1e-4.
    rel = np.sqrt((recon_sigma(l_obj) / l_obj) ** 2 + (recon_sigma(l_ref) / l_ref) ** 2)
    assert np.all(np.abs(s - truth) <= 5.5 * rel * truth)


def test_flat_field_stack_with_per_frame_polar_and_dark_reference_is_nan():
    ref = np.ones((2, 8, 8), dtype=np.float32)
    ref[:, :2, :] = 0.01  # the source barely reaches these rows
    obj = 0.5 * ref
    s = flat_field(obj, ref, reference_reflectance=1.0, polar_deg=[30.0, 60.0])
    assert np.all(np.isnan(s[:, :2]))
    np.testing.assert_allclose(s[0, 2:], 0.5 * np.cos(np.deg2rad(30.0)), rtol=1e-6)
    np.testing.assert_allclose(s[1, 2:], 0.5 * np.cos(np.deg2rad(60.0)), rtol=1e-6)
    # Frames shared by threads: the very same values.
    threaded = flat_field(obj, ref, reference_reflectance=1.0, polar_deg=[30.0, 60.0], workers=2)
    np.testing.assert_array_equal(threaded, s)


@pytest.mark.parametrize(
    ("kwargs", "culprit"),
    [
        ({"reference_radiance": np.ones((4, 5))}, "reference_radiance"),
        ({"object_radiance": np.ones(5)}, "object_radiance"),
        ({"reference_reflectance": 0.0}, "reference_reflectance"),
        ({"polar_deg": 90.0}, "polar_deg"),
        ({"polar_deg": [30.0, 40.0]}, "polar_deg"),
        ({"min_reference_fraction": 1.0}, "min_reference_fraction"),
    ],
)
def test_flat_field_rejects_bad_input(kwargs, culprit):
    args = {
        "object_radiance": np.ones((4, 4)),
        "reference_radiance": np.ones((4, 4)),
        "reference_reflectance": 1.0,
        "polar_deg": 45.0,
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=culprit):
        flat_field(args.pop("object_radiance"), args.pop("reference_radiance"), **args)
