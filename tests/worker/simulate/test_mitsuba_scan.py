"""The Mitsuba instrument: conforming bundles, agreement with the native renderer where the
two must agree (Lambertian, no interreflection), and fringe phase that gives true heights.

Tiny scenes only (48×36 px, a handful of azimuths, few samples per pixel).
"""

from __future__ import annotations

import dataclasses
import json

# The 'mitsuba' extra is part of `make setup` (pyproject's `all`): a missing renderer fails
# here rather than skipping the second instrument's tests.
import mitsuba  # noqa: F401  (the extra is installed by make setup: fail, never skip)
import numpy as np
import pytest
import trimesh

import worker.simulate.mitsuba as mitsuba_scan
from worker.bundle import open_bundle, validate_bundle
from worker.simulate.__main__ import main
from worker.simulate.acquisition import Preset
from worker.simulate.noise import noise_model
from worker.simulate.physics import PHYSICS_VARIANTS, draw_physics
from worker.simulate.projector import fringe_profile
from worker.simulate.scan import simulate_scan

SIZE = (48, 36)
TINY = Preset(
    "tiny",
    *SIZE,
    2,
    photometric_deg=(0.0, 90.0, 225.0),
    color_deg=(90.0,),
    fringe_deg=(90.0,),
)
# The default camera without the native Blinn–Phong lobe: the BSDF is Mitsuba's business.
NO_LOBE = dataclasses.replace(noise_model("default"), name="default", specular_weight=0.0)


def _grid_mesh(path, height_mm, half_x_mm=14.0, half_y_mm=11.0, n=161):
    """A height field z = -height_mm(x, y) on a rectangle as a closed-enough mesh file (mm,
    obverse toward -z): the top surface plus a flat back 3 mm below it."""
    xs, ys = np.linspace(-half_x_mm, half_x_mm, n), np.linspace(-half_y_mm, half_y_mm, n)
    gx, gy = np.meshgrid(xs, ys)
    top = np.stack([gx, gy, -height_mm(gx, gy)], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, d, c], -1), np.stack([a, c, b], -1)]).reshape(-1, 3)
    trimesh.Trimesh(top, faces, process=False).export(path)
    return path


def test_bundle_validates_and_ground_truth_has_the_native_layout(tmp_path):
    res = mitsuba_scan.render_scan_mitsuba(tmp_path, seed=3, preset=TINY, spp=4)
    bundle = res.bundles["obverse"]
    assert validate_bundle(bundle) == []
    with open_bundle(bundle) as b:
        kinds = [f.kind for f in b.frames]
        assert kinds.count("photometric") == 2 * 3
        assert kinds.count("color") == 2 * 3
        assert kinds.count("fringe") == 2 * 10 * 4
        assert b.manifest.scan.id.endswith("-mitsuba")
    gt = tmp_path / "gt"
    height, normals = np.load(gt / "height.npy"), np.load(gt / "normals.npy")
    albedo, mask = np.load(gt / "albedo.npy"), np.load(gt / "mask.npy")
    assert height.shape == SIZE[::-1] and height.dtype == np.float32
    assert normals.shape == (*SIZE[::-1], 3) and albedo.shape == (*SIZE[::-1], 3)
    assert mask.dtype == bool and 0.3 < mask.mean() < 0.95
    assert np.isfinite(height[mask]).all() and np.isnan(height[~mask]).all()
    assert np.allclose(np.linalg.norm(normals[mask], axis=-1), 1.0, atol=1e-4)
    assert (normals[mask][:, 2] < 0).all()
    # The same surface as the native view (same h = 0): point samples at the pixel centres
    # against the native box means over 2×2 supersamples.
    native = res.views["obverse"].ground_truth()
    assert (mask <= native["mask"]).all()
    assert np.median(np.abs(height - native["height"])[mask]) < 5.0
    tilt = np.degrees(np.arccos(np.clip(np.sum(normals * native["normals"], -1), -1, 1)))
    assert np.median(tilt[mask]) < 3.0
    physics = json.loads((gt / "physics.json").read_text())
    assert physics["renderer"] == "mitsuba" and physics["spp"] == 4
    assert physics["simulator"]["name"] == "worker.simulate.mitsuba"
    area = np.load(gt / "height_area.npy")
    assert np.median(np.abs(area - height)[mask]) < 5.0
    assert physics["clay"]["model"] == "roughplastic"
    assert "wedges" in json.loads((gt / "wedges.json").read_text())


def test_two_instruments_agree_on_a_lambertian_scene(tmp_path):
    """The same photometric and colour frames from both renderers: a smooth bump, diffuse
    clay, direct light only (max_depth 2), the same rig, exposures and camera. Per frame,
    the radiance read back from the two bundles differs by a median bias under 1 % and
    pixel by pixel by no more than the two frames' camera noise: z = ΔL / (√2·σ(L)) with
    σ from ``NoiseModel.radiance_sigma`` has median |z| near 0.674, the Gaussian value."""

    def bump(x, y):
        return 1.2 * np.exp(-(x**2 + y**2) / 40.0) + 0.02 * x

    mesh = _grid_mesh(tmp_path / "bump.ply", bump)
    native = simulate_scan(
        tmp_path / "native", seed=5, preset="quick", size=SIZE, noise=NO_LOBE, mesh=mesh
    )
    pbr = mitsuba_scan.render_scan_mitsuba(
        tmp_path / "mitsuba",
        seed=5,
        preset=TINY,
        noise=NO_LOBE,
        mesh=mesh,
        spp=16,
        max_depth=2,
        clay=mitsuba_scan.Clay("diffuse"),
    )
    mask = np.load(tmp_path / "mitsuba" / "gt" / "mask.npy")
    assert mask.mean() > 0.5
    with open_bundle(native.bundles["obverse"]) as a, open_bundle(pbr.bundles["obverse"]) as b:
        compared = 0
        for fb in b.frames:
            if fb.kind not in ("photometric", "color"):
                continue
            fa = a.frames_where(
                kind=fb.kind, target=fb.target, azimuth_deg=fb.azimuth_deg, channel=fb.channel
            )
            assert len(fa) == 1
            la, lb = a.radiance(fa[0]), b.radiance(fb)
            region = mask if fb.target == "object" else np.ones_like(mask)
            sigma = np.sqrt(2) * np.vectorize(NO_LOBE.radiance_sigma)(la[region])
            z = (lb - la)[region] / sigma
            bias = np.median((lb - la)[region] / la[region])
            # Measured: |bias| <= 0.4 %, median |z| 0.63-0.72 (0.674 for camera noise alone).
            assert abs(bias) < 0.01, (fb.file, bias)
            assert np.median(np.abs(z)) < 0.85, (fb.file, np.median(np.abs(z)))
            assert abs(np.median(z)) < 0.2, (fb.file, np.median(z))
            # and not by luck: the frames carry the shading (one azimuth differs from another)
            compared += 1
        assert compared == 2 * (3 + 3)
        f0 = b.frames_where(kind="photometric", target="object", azimuth_deg=0.0)[0]
        f1 = b.frames_where(kind="photometric", target="object", azimuth_deg=225.0)[0]
        assert np.median(np.abs(b.radiance(f0) - b.radiance(f1))[mask]) > 0.01


def _phase(bundle, frames):
    """Four-step phase ψ with I_k = A + B·cos(ψ + k·90°), and the modulation B/A."""
    i0, i1, i2, i3 = (bundle.radiance(f) for f in sorted(frames, key=lambda f: f.phase_deg))
    return np.arctan2(i3 - i1, i0 - i2), 0.5 * np.hypot(i3 - i1, i0 - i2) / np.maximum(
        0.25 * (i0 + i1 + i2 + i3), 1e-9
    )


def test_fringe_phase_gives_the_true_height_of_a_tilted_plane(tmp_path):
    """Δψ = -2π·h·tanθ/P (SCAN_BUNDLE.md): the object-minus-reference phase of every period
    of 4 pixels or more matches the ground-truth heights of a tilted plane (1-2 mm of
    relief) to a couple of µm, and the ground truth is the plane."""
    slope_x, slope_y = 0.05, -0.03

    def plane(x, y):
        return slope_x * x + slope_y * y

    mesh = _grid_mesh(tmp_path / "plane.ply", plane, n=9)
    preset = dataclasses.replace(TINY, photometric_deg=(0.0,), color_deg=(), fringe_deg=(90.0, 0.0))
    mitsuba_scan.render_scan_mitsuba(
        tmp_path,
        seed=2,
        preset=preset,
        noise="clean",
        mesh=mesh,
        spp=8,
        max_depth=2,
        clay=mitsuba_scan.Clay("diffuse"),
    )
    height, mask = np.load(tmp_path / "gt" / "height.npy"), np.load(tmp_path / "gt" / "mask.npy")
    # The ground truth is the plane: h(x, y) = -(z) with z = -plane, up to the offset that
    # puts h = 0 midway; so its slopes are the plane's.
    with open_bundle(tmp_path / "bundle") as b:
        s = b.manifest.camera.pixel_size_um
        rows, cols = np.nonzero(mask)
        fit = np.linalg.lstsq(
            np.stack([cols * s, rows * s, np.ones(rows.size)], -1), height[mask], rcond=None
        )[0]
        assert fit[0] == pytest.approx(slope_x, abs=1e-4)
        assert fit[1] == pytest.approx(slope_y, abs=1e-4)
        tan = np.tan(np.radians(b.manifest.source.polar_deg))
        checked = 0
        for az in (0.0, 90.0):
            periods = sorted(
                {f.period_um for f in b.frames if f.kind == "fringe" and f.azimuth_deg == az}
            )
            for period in periods:
                sets = {
                    t: b.frames_where(kind="fringe", target=t, azimuth_deg=az, period_um=period)
                    for t in ("object", "reference")
                }
                psi_o, mod_o = _phase(b, sets["object"])
                psi_r, _ = _phase(b, sets["reference"])
                expected = -2 * np.pi * height * tan / period
                err_um = (
                    np.angle(np.exp(1j * (psi_o - psi_r - expected))) * period / (2 * np.pi * tan)
                )
                if period < 4 * s:  # the finest periods alias at 48 px
                    continue
                core = mask & (mod_o > 0.3)
                assert core.sum() > 0.9 * mask.sum()
                # Measured: |median| <= 0.03 µm, median |error| 0.4 µm (P = 3.4-9.1 mm).
                assert abs(np.median(err_um[core])) < 2.0, (az, period)
                assert np.median(np.abs(err_um[core])) < 2.0, (az, period)
                checked += 1
        assert checked == 2 * 6  # n = 8, 4, 2, 1, 0.5, 0.25 periods across the field


def test_cli_renders_with_mitsuba_and_refuses_bad_arguments(tmp_path, capsys):
    assert main(["--out", str(tmp_path / "a"), "--renderer", "mitsuba", "--spp", "0"]) == 2
    assert "spp" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "b"), "--renderer", "mitsuba", "--face", "all"]) == 2
    assert "one face at a time" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["--out", str(tmp_path / "c"), "--spp", "4"])
    assert exc.value.code == 2
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    code = main(
        ["--out", str(tmp_path / "d"), "--renderer", "mitsuba", "--size", "32x24", "--spp", "1"]
    )
    assert code == 0
    assert validate_bundle(tmp_path / "d" / "bundle") == []


def test_physics_variants_reach_the_mitsuba_instrument(tmp_path):
    """A drawn Physics sets the camera (bit depth, γ, PSF and its calibration, exposures,
    hot pixels), the projector profile (here a staircase with levels, response and
    defocus, phase-step errors: one render per fringe frame), the support and the clay;
    the bundle stays conforming and the draw is recorded."""
    res = mitsuba_scan.render_scan_mitsuba(
        tmp_path / "paper", seed=2, preset=TINY, spp=2, physics="paper-like"
    )
    assert validate_bundle(res.bundles["obverse"]) == []
    with open_bundle(res.bundles["obverse"]) as b:
        assert b.manifest.camera.bit_depth == 10
        assert b.manifest.camera.psf_sigma_px == pytest.approx(0.5)
        # a 10-bit camera stores values below 2^10
        assert max(int(b.raw(f).max()) for f in b.frames[:5]) <= 1023
        fringe = b.frames_where(kind="fringe", target="reference", azimuth_deg=90.0)
        periods = sorted({f.period_um for f in fringe})
        coarse = [f for f in fringe if f.period_um == periods[-3]]
        i0, i1, i2, i3 = (b.radiance(f) for f in sorted(coarse, key=lambda f: f.phase_deg))
        mod = 0.5 * np.hypot(i3 - i1, i0 - i2) / (0.25 * (i0 + i1 + i2 + i3))
        # The projector's own profile (staircase, levels, response, defocus): its fundamental.
        pp = PHYSICS_VARIANTS["paper-like"]
        s_um = np.linspace(0, periods[-3], 4096, endpoint=False)
        profile = fringe_profile(
            s_um,
            period_um=periods[-3],
            phase_rad=0.0,
            modulation=pp.modulation,
            defocus_um=pp.projector_defocus_um,
            pixel_um=pp.projector_pixel_um,
            levels=pp.projector_levels,
            gamma=pp.projector_gamma,
        )
        fundamental = 2 * abs(np.mean(profile * np.exp(-2j * np.pi * s_um / periods[-3])))
        assert fundamental > 0.85  # γ 1.3 raises it above m = 0.8
        assert np.median(mod) == pytest.approx(fundamental, abs=0.03)
    physics = json.loads((tmp_path / "paper" / "gt" / "physics.json").read_text())
    assert physics["physics"]["name"] == "paper-like"
    assert physics["physics"]["projector_levels"] == 256
    assert any("subsurface" in n for n in physics["physics_not_modelled"])

    drawn = mitsuba_scan.render_scan_mitsuba(
        tmp_path / "random", seed=2, preset=TINY, spp=2, physics="random", physics_seed=7
    )
    assert validate_bundle(drawn.bundles["obverse"]) == []
    doc = json.loads((tmp_path / "random" / "gt" / "physics.json").read_text())
    assert doc["physics"]["name"] == "random-7" and doc["physics_seed"] == 7
    expected = draw_physics(7)
    with open_bundle(drawn.bundles["obverse"]) as b:
        assert b.manifest.camera.bit_depth == expected.bit_depth
    assert doc["clay"] == dataclasses.asdict(mitsuba_scan.clay_for(expected, 2))


def test_scalar_and_llvm_variants_render_the_same_scan(tmp_path):
    """The fallback variant (no libLLVM) gives the same ground truth and the same frames up
    to Monte Carlo noise (measured: median 0.3 % on the object, 0.0-0.2 % on the target)."""
    from worker.simulate.mitsuba.backend import _newest_libllvm

    # scripts/setup.sh installs Debian's libllvm19; without it llvm_ad_rgb cannot be compared.
    assert _newest_libllvm() is not None, "no libLLVM >= 17: run `make setup` (libllvm19)"
    preset = dataclasses.replace(TINY, photometric_deg=(0.0, 135.0), color_deg=(), fringe_deg=())
    out = {}
    for variant in ("scalar_rgb", "llvm_ad_rgb"):
        res = mitsuba_scan.render_scan_mitsuba(
            tmp_path / variant, seed=4, preset=preset, noise="clean", spp=16, variant=variant
        )
        doc = json.loads((tmp_path / variant / "gt" / "physics.json").read_text())
        assert doc["variant"] == variant
        out[variant] = res.bundles["obverse"]
    height = [np.load(tmp_path / v / "gt" / "height.npy") for v in out]
    np.testing.assert_array_equal(height[0], height[1])
    mask = np.load(tmp_path / "llvm_ad_rgb" / "gt" / "mask.npy")
    with open_bundle(out["scalar_rgb"]) as a, open_bundle(out["llvm_ad_rgb"]) as b:
        for fa, fb in zip(a.frames, b.frames, strict=True):
            if fa.kind == "dark":
                continue
            la, lb = a.radiance(fa), b.radiance(fb)
            region = (mask if fa.target == "object" else np.ones_like(mask)) & (la > 0.01)
            assert region.mean() > 0.3
            assert np.median(np.abs(la - lb)[region] / la[region]) < 0.01, fa.file


def test_cli_says_how_to_install_mitsuba_when_it_is_missing(tmp_path, capsys, monkeypatch):
    import worker.simulate.mitsuba.scan as scan_module
    from worker.simulate.mitsuba.backend import MitsubaUnavailable

    def missing(variant="auto"):
        raise MitsubaUnavailable("the mitsuba renderer needs Mitsuba 3: pip install ...")

    monkeypatch.setattr(scan_module, "load_mitsuba", missing)
    code = main(["--out", str(tmp_path / "x"), "--renderer", "mitsuba", "--size", "32x24"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: the mitsuba renderer needs Mitsuba 3")
    assert "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_interreflection_comes_from_the_renderer(tmp_path):
    """A V-groove lights itself: with one bounce (max_depth 3) its walls get brighter than
    with direct light only (max_depth 2), while the flat top far from it does not change."""

    def groove(x, y):  # 1.2 mm deep, 4 mm wide, along y, on a flat top
        return -np.clip(1.2 - 0.6 * np.abs(x), 0.0, None)

    mesh = _grid_mesh(tmp_path / "groove.ply", groove, n=281)
    preset = dataclasses.replace(TINY, photometric_deg=(0.0,), color_deg=(), fringe_deg=())
    radiance = {}
    for depth in (2, 3):
        res = mitsuba_scan.render_scan_mitsuba(
            tmp_path / str(depth),
            seed=1,
            preset=preset,
            noise="clean",
            mesh=mesh,
            spp=16,
            max_depth=depth,
            clay=mitsuba_scan.Clay("diffuse"),
        )
        with open_bundle(res.bundles["obverse"]) as b:
            radiance[depth] = b.radiance(b.frames_where(kind="photometric", target="object")[0])
    height = np.load(tmp_path / "3" / "gt" / "height.npy")
    mask = np.load(tmp_path / "3" / "gt" / "mask.npy")
    top = np.nanmax(height)
    in_groove = mask & (height < top - 400.0)
    flat = mask & (height > top - 1.0)
    gain = radiance[3] / np.maximum(radiance[2], 1e-6)
    assert in_groove.sum() > 10 and flat.sum() > 100
    assert np.median(gain[in_groove]) > 1.03  # measured 1.046 (clay albedo ~0.34)
    assert abs(np.median(gain[flat]) - 1.0) < 0.005


def test_gt_albedo_is_what_the_frames_measure_under_the_coating(tmp_path):
    """Rough plastic dims its diffuse base (κ < 1, rougher: dimmer); gt/albedo carries κ, so
    object/reference radiance x the target's reflectance gives the gt albedo on a flat
    plate (the specular lobe off so that only the diffuse part is compared)."""

    def flat(x, y):
        return 0.0 * x

    mesh = _grid_mesh(tmp_path / "flat.ply", flat, n=9)
    preset = dataclasses.replace(TINY, photometric_deg=(0.0,), color_deg=(), fringe_deg=())
    clay = mitsuba_scan.Clay("roughplastic", alpha=0.4, specular=0.0)
    res = mitsuba_scan.render_scan_mitsuba(
        tmp_path, seed=1, preset=preset, noise="clean", mesh=mesh, spp=16, clay=clay
    )
    physics = json.loads((tmp_path / "gt" / "physics.json").read_text())
    assert 0.5 < physics["clay_diffuse_factor"] < 0.7  # measured 0.67 at α 0.3, 0.53 at 0.5
    albedo = np.load(tmp_path / "gt" / "albedo.npy").mean(axis=-1)  # white light: grey
    mask = np.load(tmp_path / "gt" / "mask.npy")
    with open_bundle(res.bundles["obverse"]) as b:
        obj = b.frames_where(kind="photometric", target="object")[0]
        measured = b.radiance(obj) / b.radiance(b.reference_of(obj))
        measured *= b.manifest.reference.reflectance
    ratio = np.median(measured[mask] / albedo[mask])
    assert ratio == pytest.approx(1.0, abs=0.03)
