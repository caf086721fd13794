"""A whole scan rendered by Mitsuba 3: the bundle and ground truth of ``worker.simulate``.

Only the light transport differs from the native simulator: the same tablet and view
(``render_view`` / ``render_mesh_view``), the same instrument (``scan_rig``: irradiance
fields E, fringe phase offsets δ₀, channel gains, fixed pattern), the same frame plan
(``plan_frames``) and the same camera (``encode_frame``). Shading, cast shadows,
highlights and interreflections come from Mitsuba's path tracer on a triangle mesh of the
surface with a rough-plastic (or diffuse) clay BSDF; the camera PSF is the film's filter.

Light is linear in the emitted radiance, so one render per fringe component serves every
phase step: with the texture E·(1 + m·cos(a + δ)) = E + m·(cos δ·E cos a - sin δ·E sin a)
and E cos a = 2·E(1 + cos a)/2 - E, three non-negative textures E, E(1 + cos a)/2 and
E(1 + sin a)/2 per (azimuth, period) give the four frames (``rig._fringe_terms`` does the
same). Renders of one light direction share their random numbers, so the Monte Carlo
error is one realisation per direction and the four phases stay consistent.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from worker.bundle import write_bundle
from worker.simulate.acquisition import (
    PHASES_DEG,
    PRESETS,
    Preset,
    frame_file,
    manifest,
    pixel_size_for,
    plan_frames,
)
from worker.simulate.meshview import MeshTablet, load_mesh, render_mesh_view
from worker.simulate.mitsuba.backend import load_mitsuba
from worker.simulate.mitsuba.scene import (
    DISTANCE_MM,
    Source,
    collimated_source,
    heightfield_mesh,
    projector_dict,
    sensor_dict,
    write_ply,
)
from worker.simulate.noise import NoiseModel, encode_frame, noise_model
from worker.simulate.physics import Physics, physics_to_dict, resolve_physics
from worker.simulate.projector import defocus_mtf, fringe_profile
from worker.simulate.rig import CHANNELS, FrameSpec, Rig
from worker.simulate.scan import SimulationResult, scan_rig, write_gt_dir
from worker.simulate.support import scale_albedo, with_support
from worker.simulate.tablet import FACE_POSES, FACES, Tablet, make_tablet
from worker.simulate.view import View, render_view

__all__ = ["Clay", "clay_for", "draw_clay", "render_scan_mitsuba"]

BSDFS = ("roughplastic", "diffuse")


@dataclass(frozen=True)
class Clay:
    """The clay's BSDF. ``roughplastic``: Mitsuba's dielectric coating (index ``int_ior``,
    GGX roughness ``alpha``, specular lobe scaled by ``specular``) over a diffuse base whose
    reflectance is the albedo texture; ``diffuse``: Lambertian with the albedo texture."""

    model: str = "roughplastic"
    alpha: float = 0.3
    specular: float = 0.5
    int_ior: float = 1.5

    def __post_init__(self) -> None:
        if self.model not in BSDFS:
            raise ValueError(f"clay: model must be one of {BSDFS}, got {self.model!r}")
        if not 0.001 <= self.alpha <= 1.0:
            raise ValueError(f"clay: alpha must be in [0.001, 1], got {self.alpha}")
        if not 0.0 <= self.specular <= 1.0:
            raise ValueError(f"clay: specular must be in [0, 1], got {self.specular}")
        if not 1.0 < self.int_ior <= 3.0:
            raise ValueError(f"clay: int_ior must be in (1, 3], got {self.int_ior}")

    def bsdf(self, albedo_texture: dict, *, twosided: bool) -> dict:
        if self.model == "diffuse":
            out = {"type": "diffuse", "reflectance": albedo_texture}
        else:
            out = {
                "type": "roughplastic",
                "distribution": "ggx",
                "alpha": self.alpha,
                "int_ior": self.int_ior,
                "specular_reflectance": {"type": "rgb", "value": [self.specular] * 3},
                "diffuse_reflectance": albedo_texture,
                "nonlinear": False,
            }
        return {"type": "twosided", "bsdf": out} if twosided else out


def draw_clay(seed: int) -> Clay:
    """A rough-plastic clay drawn from ``seed``: roughness 0.1–0.5, specular scale 0.1–1."""
    rng = np.random.default_rng([seed, 0xC1A7])
    return Clay("roughplastic", float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.1, 1.0)))


def clay_for(physics: Physics, seed: int) -> Clay:
    """The clay of a drawn instrument: its strongest specular lobe (weight w, Blinn–Phong
    exponent n) as GGX roughness α = √(2/(n + 2)) (the Blinn–Phong/Beckmann correspondence
    of Walter et al. 2007, "Microfacet models for refraction", Eq. 30) and a specular scale
    w/0.2 (issue 14's lobe weights run 0–0.2); no lobe: diffuse clay; lobes left to the
    noise preset (None): ``draw_clay(seed)``."""
    if physics.specular_lobes is None:
        return draw_clay(seed)
    lobes = [lb for lb in physics.specular_lobes if lb[0] > 0]
    if not lobes:
        return Clay("diffuse")
    weight, exponent = max(lobes)
    alpha = float(np.clip(np.sqrt(2.0 / (exponent + 2.0)), 0.01, 1.0))
    return Clay("roughplastic", alpha, float(np.clip(weight / 0.2, 0.0, 1.0)))


def diffuse_factor(mi, clay: Clay, polar_deg: float, spp: int = 16) -> float:
    """κ: radiance of the clay's diffuse part over that of a Lambertian surface of the same
    base reflectance, lit at ``polar_deg`` and seen along the normal (the rig's geometry).

    Mitsuba's roughplastic weights the base's light by the rough coating's transmittance
    in and out and its internal reflection (t_i·t_o / (η²·(1 - R_int))), which depends on
    the roughness: measured κ = 0.90, 0.67, 0.53 at α = 0.1, 0.3, 0.5 (η = 1.5, 45°).
    Measured by rendering a flat patch with the specular lobe off, so gt/albedo = κ·ρ is
    the reflectance relative to a perfect white that a reflectance measurement sees.
    """
    if clay.model == "diffuse":
        return 1.0
    theta = np.radians(polar_deg)
    light = [float(-np.sin(theta)), 0.0, float(np.cos(theta))]  # travelling toward +z
    grey = {"type": "rgb", "value": 0.5}
    radiance = []
    for bsdf in (
        dataclasses.replace(clay, specular=0.0).bsdf(grey, twosided=False),
        {"type": "diffuse", "reflectance": grey},
    ):
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "path", "max_depth": 2},
                "sensor": {
                    "type": "orthographic",
                    "to_world": mi.ScalarTransform4f().translate([0, 0, -10.0])
                    @ mi.ScalarTransform4f().scale([0.5, 0.5, 1.0]),
                    "film": {
                        "type": "hdrfilm",
                        "width": 8,
                        "height": 8,
                        "rfilter": {"type": "box"},
                    },
                    "sampler": {"type": "independent", "sample_count": spp},
                },
                "patch": {
                    "type": "rectangle",
                    "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 180.0),
                    "bsdf": bsdf,
                },
                "light": {"type": "directional", "direction": light, "irradiance": 1.0},
            }
        )
        radiance.append(float(np.mean(np.array(mi.render(scene, seed=0)))))
    return radiance[0] / radiance[1]


def _first_hits(mi, variant: str, scene, x_mm: np.ndarray, y_mm: np.ndarray, z0_mm: float):
    """Mitsuba's first intersection along +z from (x, y, z0): t (mm, inf: none), normals (N, 3)."""
    n = x_mm.size
    if variant.startswith("scalar"):
        t = np.full(n, np.inf)
        normals = np.full((n, 3), np.nan)
        for i in range(n):
            ray = mi.Ray3f(mi.Point3f(float(x_mm[i]), float(y_mm[i]), z0_mm), mi.Vector3f(0, 0, 1))
            si = scene.ray_intersect(ray)
            if si.is_valid():
                t[i] = si.t
                normals[i] = (si.n[0], si.n[1], si.n[2])
        return t, normals
    origin = mi.Point3f(
        mi.Float(x_mm.astype(np.float32)),
        mi.Float(y_mm.astype(np.float32)),
        mi.Float(np.full(n, z0_mm, np.float32)),
    )
    si = scene.ray_intersect(mi.Ray3f(origin, mi.Vector3f(0, 0, 1)))
    valid = np.array(si.is_valid(), bool)
    t = np.where(valid, np.array(si.t, float), np.inf)
    normals = np.array(si.n, float)
    if normals.shape == (3, n):
        normals = normals.T
    normals[~valid] = np.nan
    return t, normals


def _ground_truth(mi, variant: str, scene, view: View, z0_mm: float) -> dict[str, np.ndarray]:
    """Point samples at the pixel centres by Mitsuba's ray intersection (SCAN_BUNDLE.md:
    the height, normal and reflectance of the surface point seen at p = (c·s, r·s)).

    Mask: the native rule (the pixel's supersamples all see the tablet), so pixels on the
    walls of the silhouette stay out.
    """
    w, h, s = view.width, view.height, view.pixel_size_um
    gx, gy = np.meshgrid(np.arange(w) * s / 1000.0, np.arange(h) * s / 1000.0)
    t, normals = _first_hits(mi, variant, scene, gx.ravel(), gy.ravel(), z0_mm)
    height = (-(z0_mm + t) * 1000.0).reshape(h, w)
    normals = normals.reshape(h, w, 3)
    normals *= np.where(normals[..., 2:] > 0, -1.0, 1.0)  # the side facing the camera
    native = view.ground_truth()
    mask = native["mask"] & np.isfinite(height)
    height = np.where(mask, height, np.nan).astype(np.float32)
    normals = np.where(mask[..., None], normals, np.nan).astype(np.float32)
    albedo = np.where(mask[..., None], native["albedo"], np.nan).astype(np.float32)
    return {"height": height, "normals": normals, "albedo": albedo, "mask": mask}


def _resolve_preset(preset: str | Preset) -> Preset:
    if isinstance(preset, Preset):
        return preset
    if preset not in PRESETS:
        raise ValueError(f"preset: unknown {preset!r}; choose from {sorted(PRESETS)}")
    return PRESETS[preset]


def _check_args(face: str, spp: int, max_depth: int, pose) -> np.ndarray | None:
    labels = [*FACES, "other"] if pose is not None else list(FACES)
    if face == "all":
        raise ValueError("face: the mitsuba renderer renders one face at a time, not 'all'")
    if face not in labels:
        raise ValueError(f"face: unknown {face!r}; choose from {labels}")
    if not 1 <= spp <= 1 << 16:
        raise ValueError(f"spp: samples per pixel must be 1..65536, got {spp}")
    if not 2 <= max_depth <= 64:
        raise ValueError(f"max_depth: must be 2..64 (2 = direct light only), got {max_depth}")
    if pose is None:
        return None
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (3, 3) or not np.allclose(pose @ pose.T, np.eye(3), atol=1e-6):
        raise ValueError("pose: must be a 3×3 rotation matrix")
    return pose


def _light_radiance(
    frames: list[FrameSpec],
    idx: list[int],
    src: Source,
    irr: np.ndarray,
    render: Callable[[np.ndarray | None], np.ndarray],
    rig: Rig,
    physics: Physics,
    model: NoiseModel,
) -> dict[int, np.ndarray]:
    """Radiance (H, W) of the frames ``idx``, all lit by the source ``src`` whose texture
    E is ``irr``: ``render(texture)`` renders the scene (RGB) with the emitter's texture
    replaced (None: E itself).

    Lamp frames: the white render's mean over RGB (photometric) or one channel times the
    rig's gain (colour). Fringe frames: a pure sinusoid from three renders (module
    docstring); a projector's staircase, response or phase-step errors (``projector.py``,
    ``Rig.phase_step_error``) from one render per frame.
    """
    radiance: dict[int, np.ndarray] = {}
    general = not physics.projector_is_sinusoid or physics.phase_step_error_deg > 0
    az, polar = frames[idx[0]].azimuth_deg, frames[idx[0]].polar_deg
    periods = sorted({frames[i].period_um for i in idx if frames[i].kind == "fringe"})
    px, py = src.points_um[..., 0], src.points_um[..., 1]
    base = render(None)
    if not periods:
        for i in idx:
            f = frames[i]
            if f.kind == "color":
                c = CHANNELS.index(f.channel)
                radiance[i] = base[..., c] * rig.channel_gain[c]
            else:
                radiance[i] = base.mean(axis=-1)
        return radiance
    b = base.mean(axis=-1)
    ux, uy = np.sin(np.radians(az)), np.cos(np.radians(az))
    coord_um = px * ux + py * uy  # u·p' of every texel
    amp = rig.modulation_scale(az, polar, px, py)  # the physics' modulation factor A
    for period in periods:
        in_set = [i for i in idx if frames[i].period_um == period]
        if general:
            for i in in_set:
                f = frames[i]
                profile = fringe_profile(
                    coord_um,
                    period_um=period,
                    phase_rad=float(
                        np.radians(f.phase_deg)
                        + rig.phase_offset(az, polar, period)
                        + rig.phase_step_error(f)
                    ),
                    modulation=model.fringe_modulation,
                    defocus_um=physics.projector_defocus_um,
                    pixel_um=physics.projector_pixel_um,
                    levels=physics.projector_levels,
                    gamma=physics.projector_gamma,
                )
                radiance[i] = render(irr * (1 + amp * (profile - 1))).mean(-1)
            continue
        # E·(1 + A·m·cos(a + δ)) = E + m·(cos δ·E·A·cos a - sin δ·E·A·sin a), and
        # E·A·cos a = 2·E(1 + A·cos a)/2 - E with a non-negative texture (A <= 1).
        a = 2 * np.pi * coord_um / period
        c2 = 2 * render(irr * (1 + amp * np.cos(a)) / 2).mean(axis=-1) - b
        s2 = 2 * render(irr * (1 + amp * np.sin(a)) / 2).mean(axis=-1) - b
        m = model.fringe_modulation * defocus_mtf(period, physics.projector_defocus_um)
        for i in in_set:
            delta = np.radians(frames[i].phase_deg) + rig.phase_offset(az, polar, period)
            radiance[i] = b + m * (np.cos(delta) * c2 - np.sin(delta) * s2)
    return radiance


def _key_ints(*values: float) -> list[int]:
    return [int(round(v * 1000)) % (1 << 62) for v in values]


def _light_groups(frames: list[FrameSpec]) -> dict[tuple, list[int]]:
    """Frame indices per light: (target, source, azimuth, polar); darks are left out."""
    groups: dict[tuple, list[int]] = {}
    for i, f in enumerate(frames):
        if f.kind == "dark":
            continue
        source = "projector" if f.kind == "fringe" else "lamp"
        key = (f.target, source, round(f.azimuth_deg % 360, 6), round(f.polar_deg, 6))
        groups.setdefault(key, []).append(i)
    return groups


def _object_shapes(
    mi, tablet: Tablet | MeshTablet, view: View, clay: Clay, albedo_tex: dict, tmp: Path
) -> dict:
    """The scanned object's shapes: a synthetic tablet as the height field of its view (the
    support included); a mesh file as it is, on the support's height field."""
    width, height, pixel = view.width, view.height, view.pixel_size_um
    s_mm = pixel / 1000.0
    ply = tmp / "tablet.ply"
    shapes: dict = {}
    if isinstance(tablet, MeshTablet):
        verts = (tablet.vertices_um @ view.pose.T + view.translation_um) / 1000.0
        uv = np.stack(
            [
                (verts[:, 0] + s_mm / 2) / (width * s_mm),
                (verts[:, 1] + s_mm / 2) / (height * s_mm),
            ],
            -1,
        )
        write_ply(ply, verts, tablet.faces, uv)
        shapes["tablet"] = {
            "type": "ply",
            "filename": str(ply),
            "face_normals": True,
            "bsdf": clay.bsdf(albedo_tex, twosided=True),
        }
        # The support (velvet, V-block or cloth) as the view's height field where no
        # corner of a quad is on the tablet.
        sverts, sfaces, suv = heightfield_mesh(view.height_ss_um, pixel, view.supersample)
        sfaces = sfaces[~view.tablet_ss.ravel()[sfaces].any(axis=1)]
        write_ply(tmp / "support.ply", sverts, sfaces, suv)
        shapes["support"] = {
            "type": "ply",
            "filename": str(tmp / "support.ply"),
            "face_normals": True,
            "bsdf": {"type": "diffuse", "reflectance": albedo_tex},
        }
    else:
        verts, faces, uv = heightfield_mesh(view.height_ss_um, pixel, view.supersample)
        write_ply(ply, verts, faces, uv)
        shapes["tablet"] = {
            "type": "ply",
            "filename": str(ply),
            "face_normals": True,
            "bsdf": clay.bsdf(albedo_tex, twosided=False),
        }
    return shapes


def _target_shapes(mi, bounds_um: tuple[float, float, float, float], reflectance: float) -> dict:
    """The reference target: a flat matte white rectangle at h = 0 facing the camera."""
    x0, x1, y0, y1 = (v / 1000.0 for v in bounds_um)
    return {
        "target": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f()
            .translate([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
            .scale([(x1 - x0) / 2, (y1 - y0) / 2, 1.0])
            @ mi.ScalarTransform4f().rotate([1, 0, 0], 180.0),
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "rgb", "value": reflectance},
            },
        }
    }


def render_scan_mitsuba(
    out_dir: str | os.PathLike,
    *,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    face: str = "obverse",
    preset: str | Preset = "quick",
    noise: str | NoiseModel = "default",
    mesh: str | os.PathLike | None = None,
    pose: np.ndarray | None = None,
    spp: int = 16,
    max_depth: int = 3,
    clay: Clay | None = None,
    physics: str | Physics = "ideal",
    physics_seed: int | None = None,
    variant: str = "auto",
    mc_seed: int = 0,
    as_zip: bool = False,
    progress: bool = False,
) -> SimulationResult:
    """Render the scan of one face of the synthetic tablet of ``seed`` (or of the mesh file
    ``mesh``, mm, obverse toward -z) with Mitsuba 3 into ``out_dir``/bundle and /gt.

    ``spp`` samples per pixel, ``max_depth`` path length (3: one interreflection bounce),
    ``clay`` the BSDF (default: ``clay_for(physics, seed)``), ``physics`` a ``Physics``, a
    named variant or ``"random"`` (drawn from ``physics_seed``, default ``seed``): its camera
    (PSF, γ, bit depth, exposures, hot pixels, E, modulation), projector (profile,
    defocus, phase-step errors, modulation factors), support, shape, albedo scale, veil
    and lobes (as the clay) apply; interreflection is the renderer's own and light
    scattered inside the clay is not modelled (recorded in gt/physics.json).
    ``variant``: ``auto`` (llvm_ad_rgb when a libLLVM >= 17 exists, else scalar_rgb),
    ``llvm_ad_rgb`` or ``scalar_rgb``;
    ``mc_seed`` changes only the renderer's random numbers (to measure its noise).
    Raises ValueError on bad arguments, FileExistsError before overwriting,
    MitsubaUnavailable when Mitsuba cannot run.
    """
    from tqdm import tqdm

    pose = _check_args(face, spp, max_depth, pose)
    plan = _resolve_preset(preset)
    base_noise = noise if isinstance(noise, NoiseModel) else noise_model(noise)
    if physics_seed is None:
        physics_seed = seed
    elif isinstance(physics_seed, bool) or not isinstance(physics_seed, int) or physics_seed < 0:
        raise ValueError(f"physics_seed: must be an integer >= 0, got {physics_seed!r}")
    drawn = resolve_physics(physics, physics_seed)
    if mesh is not None and drawn.shape != "standard":
        drawn = dataclasses.replace(drawn, shape="standard")
    model = drawn.camera(base_noise)
    clay = clay if clay is not None else clay_for(drawn, seed)
    width, height = size or (plan.width, plan.height)
    out = Path(out_dir)
    for name in ("bundle", "bundle.zip", "gt"):
        if (out / name).exists():
            raise FileExistsError(f"out: {out / name} exists; choose an empty --out")
    mi, variant = load_mitsuba(variant)

    tablet = load_mesh(mesh) if mesh is not None else make_tablet(seed, shape=drawn.shape)
    pose = FACE_POSES[face] if pose is None else pose
    pixel = pixel_size_for(width, height)
    render = render_mesh_view if isinstance(tablet, MeshTablet) else render_view
    view = render(
        tablet, pose, width=width, height=height, pixel_size_um=pixel, supersample=plan.supersample
    )
    view = with_support(scale_albedo(view, drawn.albedo_scale), drawn.support, seed)
    rig = scan_rig(seed, width, height, pixel, base_noise, drawn)
    frames = plan_frames(
        plan,
        width=width,
        height=height,
        pixel_size_um=pixel,
        noise=model,
        rng=np.random.default_rng([seed, 0xE0]),
    )
    h_ss = view.height_ss_um
    h_tab = h_ss[view.tablet_ss]
    fringe_periods = [f.period_um for f in frames if f.kind == "fringe"]
    if fringe_periods:
        need = 2 * np.tan(np.radians(plan.polar_deg)) * float(np.max(np.abs(h_tab)))
        coarsest = min(
            max(f.period_um for f in frames if f.kind == "fringe" and f.azimuth_deg == az)
            for az in {f.azimuth_deg for f in frames if f.kind == "fringe"}
        )
        if coarsest <= need:
            raise ValueError(
                f"coarsest fringe period {coarsest:.0f} µm does not exceed 2·tanθ·max|h| = {need:.0f} µm"
            )

    z_cam = -(float(h_ss.max()) / 1000.0 + 10.0)  # the sensor plane, in front of everything
    reach_um = (float(np.max(np.abs(h_ss))) + 1000.0) * np.tan(np.radians(plan.polar_deg))
    bounds_um = (
        -0.5 * pixel - reach_um,
        (width - 0.5) * pixel + reach_um,
        -0.5 * pixel - reach_um,
        (height - 0.5) * pixel + reach_um,
    )
    albedo_tex = {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(view.albedo_ss, dtype=np.float32)),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "clamp",
    }
    face_id = [*FACES, "other"].index(face)
    images: dict[str, np.ndarray] = {}
    files = [frame_file(f, i) for i, f in enumerate(frames)]
    offset = rig.offset_e((height, width), model)

    with tempfile.TemporaryDirectory(prefix="mitsuba-scan-") as tmp:
        shapes = _object_shapes(mi, tablet, view, clay, albedo_tex, Path(tmp))
        reference_shapes = _target_shapes(mi, bounds_um, rig.reflectance_reference)
        sensor = sensor_dict(mi, width, height, pixel, model.blur_sigma_px, spp, z_cam)
        integrator = {"type": "path", "max_depth": int(max_depth)}

        def scene_dict(target: str, emitter: dict | None) -> dict:
            d = {"type": "scene", "integrator": integrator, "sensor": sensor}
            d.update(shapes if target == "object" else reference_shapes)
            if emitter is not None:
                d["emitter"] = emitter
            return d

        gt = _ground_truth(mi, variant, mi.load_dict(scene_dict("object", None)), view, z_cam)
        kappa = diffuse_factor(mi, clay, plan.polar_deg)
        gt["albedo"] = (gt["albedo"] * np.float32(kappa)).astype(np.float32)

        groups = _light_groups(frames)
        # A pure sinusoid decomposes into three textures; a projector's staircase, response
        # or per-frame phase-step errors need one render per frame.
        general = not drawn.projector_is_sinusoid or drawn.phase_step_error_deg > 0
        n_renders = sum(
            1 + (len(idx) if general else 2 * len({frames[i].period_um for i in idx}))
            if key[1] == "projector"
            else 1
            for key, idx in groups.items()
        )
        bar = tqdm(
            total=n_renders,
            desc=f"{face} mitsuba renders",
            unit="render",
            file=sys.stderr,
            disable=not progress,
        )
        radiance: dict[int, np.ndarray] = {}
        for key, idx in groups.items():
            target, source_kind, az, polar = key
            periods = sorted({frames[i].period_um for i in idx if frames[i].kind == "fringe"})
            src = collimated_source(
                az, polar, bounds_um, finest_period_um=min(periods) if periods else None
            )
            px, py = src.points_um[..., 0], src.points_um[..., 1]
            irr = rig.irradiance(source_kind, az, polar, px, py)
            emitter = projector_dict(mi, src, irr, rig.source_radiance)
            scene_g = mi.load_dict(scene_dict(target, emitter))
            # One seed per light, whatever the target: object and reference pixels then
            # integrate over the same sub-pixel positions, as a real pixel does.
            light_id = [source_kind == "projector", *_key_ints(az, polar)]
            render_seed = int(
                np.random.default_rng([seed, face_id, 0x5EED, mc_seed, *light_id]).integers(1 << 31)
            )

            def render_texture(texture: np.ndarray | None, scene_g=scene_g, seed_=render_seed):
                if texture is not None:
                    params = mi.traverse(scene_g)
                    params["emitter.irradiance.data"] = mi.TensorXf(
                        np.ascontiguousarray(texture, np.float32)[..., None]
                    )
                    params.update()
                img = np.array(mi.render(scene_g, seed=seed_, spp=spp), dtype=np.float64)
                bar.update(1)
                return img

            radiance.update(
                _light_radiance(frames, idx, src, irr, render_texture, rig, drawn, model)
            )
        bar.close()

    hot = rig.hot_e((height, width), model)
    for i, (frame, file) in enumerate(zip(frames, files, strict=True)):
        lit = radiance.get(i)
        if lit is None:
            rad = np.zeros((height, width))
        else:
            rad = lit + drawn.veil * float(lit.mean()) + model.stray_light
        rng = np.random.default_rng([seed, face_id, i])
        images[file] = encode_frame(
            rad, noise=model, exposure=frame.exposure, offset_e=offset, rng=rng, hot_e=hot
        )
    doc = manifest(
        frames,
        files,
        face=face,
        pose=pose,
        seed=seed,
        width=width,
        height=height,
        pixel_size_um=pixel,
        noise=model,
        polar_deg=plan.polar_deg,
        reflectance=rig.reflectance_reference,
        psf_sigma_px=drawn.calibrated_psf_px(base_noise),
        physics_name=drawn.name,
    )
    doc["scan"]["id"] += "-mitsuba"
    doc["scan"]["tablet"]["simulator"] = "worker.simulate.mitsuba"
    out.mkdir(parents=True, exist_ok=True)
    bundle = out / ("bundle.zip" if as_zip else "bundle")
    write_bundle(bundle, doc, images, as_zip=as_zip)
    physics = {
        "simulator": {"name": "worker.simulate.mitsuba", "version": 1},
        "renderer": "mitsuba",
        "mitsuba_version": mi.__version__,
        "variant": variant,
        "integrator": {"type": "path", "max_depth": max_depth},
        "spp": spp,
        "mc_seed": mc_seed,
        "physics_seed": physics_seed,
        "physics": physics_to_dict(drawn),
        "physics_not_modelled": [
            name
            for name, on in (
                ("subsurface_um (light scattered inside the clay)", drawn.subsurface_um > 0),
                ("interreflection, interreflection_um (the renderer's own)", True),
            )
            if on
        ],
        "clay": asdict(clay),
        "clay_diffuse_factor": kappa,
        "clay_note": "albedo.npy = clay_diffuse_factor x the BSDF's base reflectance: the "
        "roughplastic coating weights the base's light by its transmittance in and out "
        "(light at the rig's polar angle, view along the normal; diffuse_factor)",
        "geometry": "mesh file"
        if isinstance(tablet, MeshTablet)
        else "height field mesh of "
        f"the ray-cast view, {view.supersample}x{view.supersample} vertices per pixel",
        "support": drawn.support,
        "sources": {
            "type": "projector (collimated)",
            "distance_mm": DISTANCE_MM,
            "fringe_modulation": model.fringe_modulation,
            "irradiance_variation": model.irradiance_variation,
        },
        "camera": {
            "psf_sigma_px": model.blur_sigma_px,
            "film_filter": "gaussian" if model.blur_sigma_px > 0 else "box",
            "noise": asdict(model),
        },
        "reference_reflectance": rig.reflectance_reference,
        "phases_deg": list(PHASES_DEG),
    }

    gt_dir = out / "gt"
    write_gt_dir(gt_dir, gt, view, tablet, physics)
    return SimulationResult(out, {face: bundle}, {face: gt_dir}, {face: view}, len(frames))
