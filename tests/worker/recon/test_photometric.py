import numpy as np
import pytest

from worker.recon.photometric import light_directions, photometric_stereo
from worker.recon.radiometry import flat_field


def test_light_directions_follow_the_spec_convention():
    d = light_directions([0.0, 90.0], [30.0, 60.0])
    s30, c30 = np.sin(np.deg2rad(30)), np.cos(np.deg2rad(30))
    s60, c60 = np.sin(np.deg2rad(60)), np.cos(np.deg2rad(60))
    # φ = 0 lights from +y (bottom edge), φ = 90° from +x (right edge); sources above: l_z < 0.
    np.testing.assert_allclose(d, [[0, s30, -c30], [s60, 0, -c60]], atol=1e-12)


def test_exact_plane_is_recovered_from_three_lights():
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    ls = light_directions([0.0, 120.0, 240.0], [30.0, 45.0, 60.0])
    s = (0.7 * ls @ n)[:, None, None] * np.ones((3, 4, 5))
    res = photometric_stereo(s, ls)
    np.testing.assert_allclose(res.normals, np.broadcast_to(n, (4, 5, 3)), atol=1e-5)
    np.testing.assert_allclose(res.albedo, 0.7, atol=1e-5)
    assert np.all(res.lights_used == 3)


def _render(scene, ls, rho, rng, sense, *, gain=0.9):
    """Object and reference radiance of every light, E(p) uniform (flat field tested apart)."""
    cos_nl = np.einsum("hwc,kc->khw", scene.normals, ls)
    theta = np.arccos(-ls[:, 2])
    l_obj = gain * rho * np.clip(cos_nl, 0.0, None)
    l_ref = gain * np.cos(theta)[:, None, None] * np.ones_like(l_obj)
    return cos_nl, l_obj, l_ref


def _sphere_case(rng, sphere, sense, sigma, corrupt):
    """Render a noisy sphere under 12 lights, corrupt it, run flat field + photometric stereo.

    Returns the z² of every usable pixel: squared angular error over its predicted variance.
    Expected error from the noise: unweighted least squares over the true inlier set I
    (n·l > 0.1, not corrupted) gives cov(b) = A⁻¹ Lᵀ Σ L A⁻¹, A = LᵀL, Σ = diag(σ_s²) with σ_s
    the ratio noise of s = L_obj / 0.9 (ρ_ref = 1, gain 0.9); the angular error² is then
    ≈ tr(P cov P)/ρ², P the projector orthogonal to n, so z² has mean ≈ 1.
    """
    scene = sphere(64, radius_px=40.0)
    azimuths = np.arange(12) * 30.0
    polars = np.where(np.arange(12) % 2 == 0, 40.0, 55.0)
    ls = light_directions(azimuths, polars)
    rho = rng.uniform(0.3, 0.8, scene.height_um.shape)
    cos_nl, l_obj, l_ref = _render(scene, ls, rho, rng, sense)
    # Cast shadows: V = 0 for ~8 % of the samples, anywhere.
    shadowed = rng.uniform(size=l_obj.shape) < 0.08
    l_obj = np.where(shadowed, 0.0, l_obj)
    extra = np.where(shadowed, 0.0, corrupt(scene, ls, cos_nl))
    l_obj = l_obj + extra
    # A highlight below 0.002 (half a noise σ) is noise, not an outlier.
    specular = extra > 0.002
    s = flat_field(
        sense(l_obj, rng), sense(l_ref, rng), reference_reflectance=1.0, polar_deg=polars
    )
    # The cone re-solve (highlight_cone_deg) leaves out, by design, a few clean samples near
    # the mirror direction; here the inlier sets of the robust fit itself are checked
    # (test_photometric_fit.py covers the cone step).
    res = photometric_stereo(s, ls, highlight_cone_deg=None)

    true_in = (cos_nl > 0.1) & ~shadowed & ~specular
    usable = true_in.sum(axis=0) >= 5
    sig_s = np.sqrt((sigma(l_obj) / 0.9) ** 2 + (rho * cos_nl) ** 2 * (sigma(l_ref) / l_ref) ** 2)
    w = true_in.astype(float)
    a = np.einsum("khw,ki,kj->hwij", w, ls, ls)
    c = np.einsum("khw,khw,ki,kj->hwij", w, sig_s**2, ls, ls)
    ainv = np.linalg.inv(np.where(usable[..., None, None], a, np.eye(3)))
    cov = ainv @ c @ ainv
    p = np.eye(3) - scene.normals[..., :, None] * scene.normals[..., None, :]
    var_ang = np.einsum("hwij,hwjk,hwki->hw", p, cov, p) / rho**2
    cosang = np.clip(np.sum(res.normals * scene.normals, axis=-1), -1, 1)
    z2 = np.arccos(cosang)[usable] ** 2 / var_ang[usable]
    assert np.all(np.isfinite(res.normals[usable]))
    assert np.all(res.normals[usable][:, 2] < 0)
    # Lights used must equal the true inlier count wherever that count is unambiguous: no
    # highlight between noise and tolerance, no sample within reach of the terminator.
    clear = ~np.any(
        ((extra > 0.002) & (extra < 0.15)) | ((cos_nl > 0.05) & (cos_nl < 0.2)), axis=0
    )[usable]
    agree = (res.lights_used[usable] == true_in.sum(axis=0)[usable])[clear]
    albedo_err = np.median(np.abs(res.albedo[usable] / rho[usable] - 1))
    # Highlights between noise and the relative tolerance of the fit are (rightly) kept and
    # bias the normal; pixels with such a sample are "grey" and judged more loosely.
    grey = np.any((extra > 0.002) & (extra < 0.15) & (cos_nl > 0), axis=0)[usable]
    return z2, agree, albedo_err, specular.sum(), grey


def test_sphere_normals_with_cast_shadows_and_specular_highlights(
    recon_sphere, recon_sense, recon_sigma
):
    def blinn_phong(scene, ls, cos_nl):
        # Highlight of a glossy coat: 0.8·(n·h)^1000, h the half-vector of l and the view
        # direction (0, 0, −1); it lands where n bisects them, on the brightest lights.
        half = ls + np.array([0.0, 0.0, -1.0])
        half /= np.linalg.norm(half, axis=1)[:, None]
        nh = np.clip(np.einsum("hwc,kc->khw", scene.normals, half), 0, None)
        return np.where(cos_nl > 0, 0.8 * nh**1000, 0.0)

    z2, agree, albedo_err, n_spec, grey = _sphere_case(
        np.random.default_rng(7), recon_sphere, recon_sense, recon_sigma, blinn_phong
    )
    assert n_spec > 500 and np.mean(~grey) > 0.8  # the highlights are really there
    # Where every highlight is a clear outlier (≥ 0.15 in s, ≥ 30σ): mean z² is 1 for the
    # ideal estimator, 1.5 allows for inlier sets differing from the true ones near the
    # terminator; a kept highlight makes z² ≫ 100, and ~3,500 draws of z² (≈ χ²₂/2-like)
    # exceed 40 with probability ~1e-5.
    assert np.mean(z2[~grey]) < 1.5
    assert np.max(z2[~grey]) < 40.0
    # Grey pixels carry a bias of up to the tolerance; they must still be mostly close.
    assert np.median(z2[grey]) < 9.0
    # Every clear highlight and cast shadow was left out and every clean sample kept, but for
    # the highlight peeling (mirror_trim), which drops the clean sample nearest the mirror
    # direction when noise puts it 2.5 global σ above the fit: under shot noise that sample,
    # among the brightest, has up to ~1.5× the global σ, P(N > 2.5/1.5) ≈ 5 % at worst and
    # ~1 % over this sphere; 2 % is the bound.
    assert np.mean(agree) > 0.98
    # Albedo: σ_ρ/ρ ≈ σ_s/(ρ·sqrt(m/2)) ≈ 0.004/(0.5·1.7) ≈ 0.5 % with m ≈ 6 lights; the
    # median |error| of a normal variable is 0.67σ; 1.5 % catches biases, not noise.
    assert albedo_err < 0.015


def test_sphere_normals_with_spikes_on_random_lights(recon_sphere, recon_sense, recon_sigma):
    def spikes(scene, ls, cos_nl):
        # Harsher than optics: 40 % of the pixels get a spike of +0.3…0.8 on one random lit
        # light, or on two neighbouring ones, whatever their n·l.
        rng = np.random.default_rng(11)
        k = len(ls)
        h, w = scene.height_um.shape
        first = rng.integers(0, k, (h, w))
        two = rng.uniform(size=(h, w)) < 0.5
        has = rng.uniform(size=(h, w)) < 0.4
        kk = np.arange(k)[:, None, None]
        hit = has & ((kk == first) | (two & (kk == (first + 1) % k))) & (cos_nl > 0.1)
        return np.where(hit, rng.uniform(0.3, 0.8, cos_nl.shape), 0.0)

    z2, agree, albedo_err, _, _ = _sphere_case(
        np.random.default_rng(8), recon_sphere, recon_sense, recon_sigma, spikes
    )
    # Two spikes among ~6 lit lights can mimic another normal within the relative tolerance
    # in a few configurations; all but 1 % of the pixels must still be at noise level
    # (z² ≤ 25, i.e. 5σ) and the mean bounded as above.
    assert np.mean(z2 <= 25.0) > 0.99
    assert np.median(z2) < 1.0
    assert np.mean(agree) > 0.97
    assert albedo_err < 0.015


def test_pixels_with_fewer_than_three_lights_are_nan():
    ls = light_directions([0.0, 90.0, 180.0, 270.0], 45.0)
    s = np.full((4, 3, 3), 0.5, dtype=np.float32)
    s[:2, 0, 0] = np.nan  # only two samples left
    s[:, 1, 1] = 0.0  # shadowed under every light
    mask = np.ones((3, 3), dtype=bool)
    mask[2, 2] = False
    res = photometric_stereo(s, ls, mask=mask)
    for r, c in [(0, 0), (1, 1), (2, 2)]:
        assert np.all(np.isnan(res.normals[r, c])) and res.lights_used[r, c] == 0
    np.testing.assert_allclose(res.normals[0, 1], [0, 0, -1], atol=1e-5)


@pytest.mark.parametrize(
    ("shading", "lights", "culprit"),
    [
        (np.ones((2, 4, 4)), np.ones((2, 3)), "shading"),
        (np.ones((4, 4, 4)), np.ones((3, 3)), "light_dirs"),
        (np.ones((3, 4, 4)), [[0, 0, -1], [0, 0, -2], [0, 0.1, -1]], "light_dirs"),
    ],
)
def test_photometric_stereo_rejects_bad_input(shading, lights, culprit):
    with pytest.raises(ValueError, match=culprit):
        photometric_stereo(shading, np.asarray(lights, dtype=float))


def test_light_directions_reject_bad_polar():
    with pytest.raises(ValueError, match="polar_deg"):
        light_directions([0.0, 90.0], 95.0)


@pytest.mark.slow
@pytest.mark.xdist_group("recon_sim")
def test_simulated_bundle_normals_against_ground_truth(simulated_recon):
    r = simulated_recon
    err = np.arccos(np.clip(np.sum(r.normals * r.gt_normals, axis=-1), -1, 1))
    z = err[r.smooth] / r.sigma_normal_rad[r.smooth]
    # On smooth interior pixels only noise should remain: z = |error| / predicted RMS error
    # of a 2-D Gaussian has median 0.83 and 99th percentile 2.1; 1.5 and 4 leave room for
    # pixels that average a slightly curved surface.
    assert np.median(z) < 1.5
    assert np.percentile(z, 99) < 4.0
    # Every tablet pixel gets a normal (8 lights: at least 3 always see a visible point).
    assert np.mean(np.isfinite(err[r.mask])) > 0.99


def test_photometric_stereo_leaves_its_input_alone():
    rng = np.random.default_rng(10)
    ls = light_directions(np.arange(8) * 45.0, 45.0)
    s = rng.uniform(0, 1, (8, 6, 6)).astype(np.float32)
    s[0, 0, 0] = np.nan
    before = s.copy()
    photometric_stereo(s, ls)
    np.testing.assert_array_equal(s, before)


def test_threads_share_the_chunks_without_changing_the_result(monkeypatch):
    # Pixels are independent, so how the chunks are shared out must not show: the smallest
    # chunk (4096 pixels) cuts this 96 × 96 image into three, run in two threads.
    import worker.recon.photometric as ps

    rng = np.random.default_rng(11)
    ls = light_directions(np.arange(8) * 45.0, 45.0)
    n = rng.normal(0.0, 0.3, (96, 96, 3))
    n[..., 2] = -1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cos = np.einsum("hwc,kc->khw", n, ls)
    s = (0.5 * np.clip(cos, 0, None) + rng.normal(0, 0.004, cos.shape)).astype(np.float32)
    s[2, rng.uniform(size=(96, 96)) < 0.1] += 0.5  # highlights for the robust steps
    monkeypatch.setattr(ps, "_CHUNK_SAMPLES", 1)
    one = photometric_stereo(s, ls)
    two = photometric_stereo(s, ls, workers=2)
    for field in ("normals", "albedo", "residual", "lights_used"):
        np.testing.assert_array_equal(getattr(two, field), getattr(one, field))


def _dense_sphere(rng, lobe):
    """A 40 px sphere under 48 lights (rings at 20°, 35°, 50°), noise σ = 0.003, plus a
    Blinn–Phong lobe of weight `lobe`: shading, lights and true normals."""
    yy, xx = np.mgrid[0:40, 0:40] - 19.5
    r2 = (xx**2 + yy**2) / 18.0**2
    inside = r2 < 1
    n = np.stack([xx / 18.0, yy / 18.0, -np.sqrt(np.clip(1 - r2, 0, 1))], -1)
    n[~inside] = (0, 0, -1)
    ls = light_directions(np.arange(48) * 7.5, np.repeat([20.0, 35.0, 50.0], 16))
    half = ls + (0, 0, -1)
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    cos = np.einsum("hwc,kc->khw", n, ls)
    spec = lobe * np.clip(np.einsum("hwc,kc->khw", n, half), 0, 1) ** 50 * (cos > 0)
    s = 0.5 * np.clip(cos, 0, None) + spec + rng.normal(0, 0.003, cos.shape)
    return s.astype(np.float32), ls, n, inside


def _mean_error_deg(est, truth, where):
    dot = np.clip(np.sum(est * truth, -1), -1, 1)[where]
    return float(np.degrees(np.arccos(dot)).mean())


def test_least_squares_where_consistent_is_least_squares_on_a_matte_sphere():
    rng = np.random.default_rng(3)
    s, ls, n, inside = _dense_sphere(rng, lobe=0.0)
    gated = photometric_stereo(s, ls, mask=inside, least_squares_when_consistent=True)
    robust = photometric_stereo(s, ls, mask=inside)
    # Where every lit sample fits, the gated result is least squares over the lit samples:
    # none of them is an outlier.
    assert np.mean(gated.outliers[inside] == 0) > 0.9
    assert np.mean(gated.outliers[inside] == 0) > np.mean(robust.outliers[inside] == 0)
    assert _mean_error_deg(gated.normals, n, inside) <= _mean_error_deg(robust.normals, n, inside)


def test_least_squares_where_consistent_keeps_the_robust_fit_at_highlights():
    rng = np.random.default_rng(4)
    s, ls, n, inside = _dense_sphere(rng, lobe=0.5)
    gated = photometric_stereo(s, ls, mask=inside, least_squares_when_consistent=True)
    robust = photometric_stereo(s, ls, mask=inside)
    lit = np.einsum("hwc,kc->khw", n, ls) > 0.1
    w = lit.astype(float)
    a = np.einsum("khw,ki,kj->hwij", w, ls, ls) + 1e-9 * np.eye(3)
    b = np.linalg.solve(a, np.einsum("khw,khw,ki->hwi", w, s, ls)[..., None])[..., 0]
    ls_normals = b / np.linalg.norm(b, axis=-1, keepdims=True)
    e_gated = _mean_error_deg(gated.normals, n, inside)
    assert e_gated < 0.5 * _mean_error_deg(ls_normals, n, inside)
    assert e_gated == pytest.approx(_mean_error_deg(robust.normals, n, inside), rel=0.1)
    # The highlight samples are counted as outliers: lit, yet left out.
    assert gated.outliers[inside].max() >= 3


def test_consensus_light_sets_take_the_neighbourhood_majority():
    from worker.recon.photometric_fit import consensus_light_sets

    # Light 0 kept by a quarter of the pixels, light 1 by three quarters, light 2 by all;
    # the unsolved border votes for nothing.
    rng = np.random.default_rng(1)
    inl = np.ones((3, 40, 40), dtype=bool)
    inl[0] = rng.uniform(size=(40, 40)) < 0.25
    inl[1] = rng.uniform(size=(40, 40)) < 0.75
    ok = np.zeros((40, 40), dtype=bool)
    ok[2:-2, 2:-2] = True
    inl[:, ~ok] = False
    c = consensus_light_sets(inl, ok, 9)
    core = ok.copy()
    core[:6, :] = core[-6:, :] = core[:, :6] = core[:, -6:] = False
    assert c[0][core].mean() < 0.05
    assert c[1][core].mean() > 0.95
    assert c[2][ok].all()  # unsolved neighbours do not outvote the solved ones


def _biased_light_sphere(rng, bias):
    """A sphere under 8 lights at 45° whose first light reads `bias` too bright: at the fit's
    relative tolerance, so that noise decides pixel by pixel whether it is kept."""
    yy, xx = np.mgrid[0:64, 0:64] - 31.5
    r2 = (xx**2 + yy**2) / 60.0**2
    n = np.stack([xx / 60.0, yy / 60.0, -np.sqrt(1 - r2)], -1)
    ls = light_directions(np.arange(8) * 45.0, 45.0)
    s = 0.5 * np.clip(np.einsum("hwc,kc->khw", n, ls), 0, None)
    s[0] *= 1.0 + bias
    return (s + rng.normal(0, 0.004, s.shape)).astype(np.float32), ls, n


def test_consensus_window_keeps_one_light_set_over_a_neighbourhood():
    s, ls, n = _biased_light_sphere(np.random.default_rng(5), 0.12)
    own = photometric_stereo(s, ls)
    shared = photometric_stereo(s, ls, consensus_window_px=5)

    def switches(r):
        return np.mean(r.lights_used[:, 1:] != r.lights_used[:, :-1])

    def roughness(r):
        # Pixel-to-pixel jumps of the normal error: the patchwork that integrates into
        # height error.
        return np.mean(np.abs(np.diff(r.normals[..., 0] - n[..., 0], axis=1)))

    assert switches(own) > 0.15  # the patchwork is there
    assert switches(shared) < 0.5 * switches(own)
    assert roughness(shared) < 0.95 * roughness(own)


def test_consensus_window_still_rejects_highlights_and_cast_shadows():
    rng = np.random.default_rng(6)
    s, ls, n = _biased_light_sphere(rng, 0.0)
    half = ls + np.array([0.0, 0.0, -1.0])
    half /= np.linalg.norm(half, axis=1)[:, None]
    nh = np.clip(np.einsum("hwc,kc->khw", n, half), 0, None)
    s = s + (0.8 * nh**1000).astype(np.float32)  # highlights
    s[3, :, :30] = 0.0  # a cast shadow over a third of the image, sharp edge
    own = photometric_stereo(s, ls)
    shared = photometric_stereo(s, ls, consensus_window_px=5)
    e_own = _mean_error_deg(own.normals, n, np.ones(n.shape[:2], bool))
    e_shared = _mean_error_deg(shared.normals, n, np.ones(n.shape[:2], bool))
    assert e_shared < 1.1 * e_own + 0.05
    # A shadowed or highlight sample kept by the neighbourhood's set would tilt the normal
    # by degrees (0.8 above a shading of ~0.3; the shadow's 0 on a lit sample).
    err = np.degrees(np.arccos(np.clip(np.sum(shared.normals * n, -1), -1, 1)))
    assert np.max(err) < 5.0


def test_coherent_normals_stand_down_where_the_surface_turns():
    from worker.recon.photometric_fit import coherent_normals

    # A V-groove: walls tilted ±20° meet along column 20; plane beyond.
    h, w = 30, 60
    slope = np.zeros((h, w))
    slope[:, 10:20] = -np.tan(np.radians(20.0))
    slope[:, 20:30] = np.tan(np.radians(20.0))
    b = np.stack([-slope, np.zeros((h, w)), -np.ones((h, w))], -1) * 0.7  # ρ = 0.7 scale
    ok = np.ones((h, w), dtype=bool)
    ok[:, 55:] = False  # unsolved pixels neither vote nor pass
    c = coherent_normals(b, ok, 5, 12.0)
    assert not c[:, 55:].any()
    assert c[:, 40:50].all()  # flat: R̄ = 1
    assert c[:, 13:17].all() and c[:, 23:27].all()  # inside one wall
    # Windows with both walls (at least one column of each in five): R̄ ≤ 0.962 < cos 12°.
    assert not c[:, 18:22].any()
    # Within ±20° of their mean every window passes at 25°; the wall's edge on the plane
    # (0° against 20°) passes at 12° too.
    assert coherent_normals(b, ok, 5, 25.0)[:, :55].all()
    assert c[:, 8:12].all()


def test_consensus_stands_down_at_a_crease():
    # The biased light of _biased_light_sphere, on a V-groove whose walls are tilted ±20°:
    # where the window straddles the crease, each pixel keeps its own light set.
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:48, 0:64]
    t = np.tan(np.radians(20.0))
    sx = np.where(xx < 32, -t, t)
    n = np.stack([-sx, np.zeros_like(sx), -np.ones_like(sx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    ls = light_directions(np.arange(8) * 45.0, 45.0)
    s = 0.5 * np.clip(np.einsum("hwc,kc->khw", n, ls), 0, None)
    s[0] *= 1.12
    s = (s + rng.normal(0, 0.004, s.shape)).astype(np.float32)
    own = photometric_stereo(s, ls)
    strict = photometric_stereo(s, ls, consensus_window_px=5, consensus_max_turn_deg=12.0)
    loose = photometric_stereo(s, ls, consensus_window_px=5, consensus_max_turn_deg=90.0)
    crease = np.zeros(n.shape[:2], dtype=bool)
    crease[:, 30:34] = True
    same = np.all(strict.normals == own.normals, axis=-1)
    assert same[crease].all()  # stood down: the pixel's own fit, bit for bit
    assert not np.all(loose.normals[crease] == own.normals[crease])  # the set acts without it
    assert not same[:, 5:25].all()  # away from the crease it still acts


def test_consensus_options_are_checked():
    s, ls, _ = _biased_light_sphere(np.random.default_rng(8), 0.0)
    with pytest.raises(ValueError, match="consensus_max_turn_deg"):
        photometric_stereo(s, ls, consensus_window_px=5, consensus_max_turn_deg=0.0)
    with pytest.raises(ValueError, match="consensus_window_px"):
        photometric_stereo(s, ls, consensus_window_px=-1)
