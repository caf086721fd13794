"""Photometric-only bundles of objects other than tablets, rendered by Mitsuba 3: a stand-in
for real photographs such as the DiLiGenT benchmark (Shi et al. 2019, "A Benchmark Dataset
and Evaluation for Non-Lambertian and Uncalibrated Photometric Stereo", TPAMI 41(2)), which
cannot be fetched here.

Each object is a union of spheres (exact normals, concave creases where spheres meet, which
interreflect and cast shadows) resting on a dark matte ground (black velvet, reflectance
0.02), under 96 directional lights on an 8 × 12 grid like DiLiGenT's LEDs, seen by the
spec's orthographic camera. The bundle holds one dark frame and one photometric frame per
light, no reference target and no projector: what a photographer's rig gives.

``render_object_bundle(out_dir, name, ...)`` writes ``out_dir/bundle`` and ``out_dir/gt``
(height.npy, normals.npy, mask.npy: point samples at the pixel centres, SCAN_BUNDLE.md).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from worker.bundle import write_bundle
from worker.durable import npy_bytes, replace_dir_atomic, write_new_file
from worker.simulate.mitsuba.backend import load_mitsuba
from worker.simulate.mitsuba.scan import _first_hits
from worker.simulate.mitsuba.scene import sensor_dict
from worker.simulate.noise import NoiseModel, encode_frame, fixed_pattern_e

__all__ = ["CAMERA", "OBJECTS", "PhotoObject", "diligent_lights", "render_object_bundle"]

# A 16-bit scientific camera as DiLiGenT's (no PSF beyond the pixel's box, linear response).
CAMERA = NoiseModel(
    name="photo16",
    bit_depth=16,
    full_well_e=20_000.0,
    read_noise_e=10.0,
    dark_offset_e=200.0,
    fixed_pattern_e=20.0,
    dark_current_e=10.0,
    specular_weight=0.0,
    blur_sigma_px=0.0,
    irradiance_variation=0.0,
)
GROUND_REFLECTANCE = 0.02  # black velvet


@dataclass(frozen=True)
class PhotoObject:
    """Spheres (centre x, y as fractions of the field, height of the centre above the ground
    and radius as fractions of the field's width) and one BSDF for all of them:
    ``diffuse`` (ρ) or ``roughplastic`` (ρ, GGX roughness α, specular scale)."""

    name: str
    spheres: tuple[tuple[float, float, float, float], ...]
    reflectance: float
    model: str = "diffuse"
    alpha: float = 0.3
    specular: float = 1.0
    max_depth: int = 6

    def bsdf(self) -> dict:
        rho = {"type": "rgb", "value": [self.reflectance] * 3}
        if self.model == "diffuse":
            return {"type": "diffuse", "reflectance": rho}
        return {
            "type": "roughplastic",
            "distribution": "ggx",
            "alpha": self.alpha,
            "int_ior": 1.5,
            "specular_reflectance": {"type": "rgb", "value": [self.specular] * 3},
            "diffuse_reflectance": rho,
            "nonlinear": False,
        }


def _cat() -> tuple:
    """A lying cat: body, head above it, ears, paws and a tail; creases everywhere."""
    return (
        (0.50, 0.60, 0.24, 0.24),  # body
        (0.50, 0.30, 0.36, 0.15),  # head, standing above the body's front
        (0.41, 0.19, 0.44, 0.06),  # ears
        (0.59, 0.19, 0.44, 0.06),
        (0.38, 0.80, 0.06, 0.06),  # front paws
        (0.62, 0.80, 0.06, 0.06),
        (0.76, 0.70, 0.07, 0.07),  # tail along the right side
        (0.80, 0.55, 0.06, 0.06),
        (0.80, 0.40, 0.05, 0.05),
    )


def _harvest() -> tuple:
    """A heap of fruit: a mound with twelve overlapping spheres on and around it."""
    rng = np.random.default_rng(7)
    parts = [(0.50, 0.50, 0.08, 0.22)]
    for k in range(12):
        a = 2 * np.pi * k / 12 + rng.uniform(-0.2, 0.2)
        r = rng.uniform(0.08, 0.12)
        d = rng.uniform(0.18, 0.28)
        z = rng.uniform(0.05, 0.22)
        parts.append((0.5 + d * np.cos(a), 0.5 + d * np.sin(a), z, r))
    return tuple(parts)


OBJECTS: dict[str, PhotoObject] = {
    o.name: o
    for o in (
        PhotoObject("matte_ball", ((0.5, 0.5, 0.38, 0.38),), 0.6),
        PhotoObject(
            "dark_glossy_ball",
            ((0.5, 0.5, 0.38, 0.38),),
            0.05,
            model="roughplastic",
            alpha=0.12,
            specular=1.0,
        ),
        PhotoObject("cat", _cat(), 0.55, model="roughplastic", alpha=0.35, specular=0.4),
        PhotoObject("harvest", _harvest(), 0.45, model="roughplastic", alpha=0.08, specular=1.0),
    )
}


def diligent_lights() -> tuple[np.ndarray, np.ndarray]:
    """(azimuth°, polar°) of 96 lights on an 8 × 12 grid on a plane in front of the object
    (DiLiGenT's LED board): l ∝ (x, y, −1), x ∈ [−0.8, 0.8], y ∈ [−0.6, 0.6], polar 5°–45°."""
    xs, ys = np.linspace(-0.8, 0.8, 12), np.linspace(-0.6, 0.6, 8)
    gx, gy = np.meshgrid(xs, ys)
    x, y = gx.ravel(), gy.ravel()
    polar = np.degrees(np.arctan(np.hypot(x, y)))
    azimuth = np.degrees(np.arctan2(x, y)) % 360.0
    return azimuth, polar


def _sensor(mi, size: int, pixel_mm: float, spp: int, z_mm: float) -> dict:
    return sensor_dict(mi, size, size, pixel_mm * 1000.0, 0.0, spp, z_mm)


def _spheres(mi, obj: PhotoObject, field_mm: float) -> dict:
    return {
        f"part{i}": {
            "type": "sphere",
            "center": [x * field_mm, y * field_mm, -z * field_mm],
            "radius": r * field_mm,
            "bsdf": obj.bsdf(),
        }
        for i, (x, y, z, r) in enumerate(obj.spheres)
    }


def _ground(mi, field_mm: float) -> dict:
    T = mi.ScalarTransform4f
    c = field_mm / 2
    return {
        "ground": {
            "type": "rectangle",
            "to_world": T().translate([c, c, 0.0]).scale([4 * c, 4 * c, 1.0])
            @ T().rotate([1, 0, 0], 180.0),
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "rgb", "value": GROUND_REFLECTANCE},
            },
        }
    }


def _ground_truth(mi, variant, scene, size: int, pixel_mm: float, z0_mm: float) -> dict:
    g = np.arange(size) * pixel_mm
    gx, gy = np.meshgrid(g, g)
    t, normals = _first_hits(mi, variant, scene, gx.ravel(), gy.ravel(), z0_mm)
    mask = np.isfinite(t).reshape(size, size)
    height = np.where(mask, -(z0_mm + t.reshape(size, size)) * 1000.0, np.nan)
    normals = normals.reshape(size, size, 3)
    normals *= np.where(normals[..., 2:] > 0, -1.0, 1.0)  # the side facing the camera
    normals = np.where(mask[..., None], normals, np.nan)
    return {
        "height": height.astype(np.float32),
        "normals": normals.astype(np.float32),
        "mask": mask,
    }


def render_object_bundle(
    out_dir: str | Path,
    name: str,
    *,
    size: int = 128,
    pixel_size_um: float = 100.0,
    spp: int = 16,
    seed: int = 0,
    variant: str = "auto",
    camera: NoiseModel = CAMERA,
) -> tuple[Path, Path]:
    """Render object ``name`` (one of ``OBJECTS``) into ``out_dir``/bundle and /gt; returns
    both paths. The exposure puts the stack's 99.9th percentile at 90 % of full scale, as a
    photographer would (highlights above it clip). Raises ValueError on a bad argument,
    FileExistsError before overwriting, MitsubaUnavailable when Mitsuba cannot run."""
    if name not in OBJECTS:
        raise ValueError(f"object: unknown {name!r}; choose from {sorted(OBJECTS)}")
    if not 16 <= size <= 4096:
        raise ValueError(f"size: must be 16..4096 px, got {size}")
    out = Path(out_dir)
    for sub in ("bundle", "gt"):
        if (out / sub).exists():
            raise FileExistsError(f"out: {out / sub} exists; choose an empty folder")
    obj = OBJECTS[name]
    mi, variant = load_mitsuba(variant)
    pixel_mm = pixel_size_um / 1000.0
    field_mm = size * pixel_mm
    z_cam = -2.0 * field_mm
    sensor = _sensor(mi, size, pixel_mm, spp, z_cam)
    shapes = _spheres(mi, obj, field_mm)
    gt = _ground_truth(
        mi, variant, mi.load_dict({"type": "scene", **shapes}), size, pixel_mm, z_cam
    )
    T = mi.ScalarTransform4f
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": obj.max_depth},
            "sensor": sensor,
            **shapes,
            **_ground(mi, field_mm),
            # A white diffuser facing the light has radiance irradiance/π = 1.
            "light": {"type": "directional", "irradiance": float(np.pi)},
        }
    )
    params = mi.traverse(scene)
    azimuth, polar = diligent_lights()
    phi, theta = np.radians(azimuth), np.radians(polar)
    radiance = []
    for k in range(azimuth.size):
        toward = np.array(
            [
                np.sin(theta[k]) * np.sin(phi[k]),
                np.sin(theta[k]) * np.cos(phi[k]),
                -np.cos(theta[k]),
            ]
        )
        # The emitter shines along its local +z: from the light toward the object, −l.
        params["light.to_world"] = T().look_at(
            origin=[0.0, 0.0, 0.0], target=(-toward).tolist(), up=[0.0, 1.0, 0.0]
        )
        params.update()
        img = np.array(mi.render(scene, seed=int(seed * 1000 + k), spp=spp), np.float64)
        radiance.append(img.mean(axis=-1))
    stack = np.stack(radiance)
    gain = 0.9 / max(float(np.percentile(stack, 99.9)), 1e-6)
    rng = np.random.default_rng([seed, 0x0B1])
    offset = fixed_pattern_e((size, size), camera, seed)
    files = ["dark.png"] + [f"photo_{k:03d}.png" for k in range(azimuth.size)]
    images = {
        "dark.png": encode_frame(
            np.zeros((size, size)), noise=camera, exposure=1.0, offset_e=offset, rng=rng
        )
    }
    frames: list[dict] = [{"file": "dark.png", "kind": "dark"}]
    for k in range(azimuth.size):
        images[files[k + 1]] = encode_frame(
            stack[k] * gain, noise=camera, exposure=1.0, offset_e=offset, rng=rng
        )
        frames.append(
            {
                "file": files[k + 1],
                "kind": "photometric",
                "azimuth_deg": float(azimuth[k]),
                "polar_deg": float(polar[k]),
            }
        )
    doc = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {
            "id": f"photo-{name}-{size}-{seed}",
            "face": "other",
            "tablet": {"designation": f"rendered object {name}", "simulator": __name__},
        },
        "camera": {
            "width": size,
            "height": size,
            "pixel_size_um": pixel_size_um,
            "bit_depth": camera.bit_depth,
        },
        "source": {"polar_deg": float(np.median(polar))},
        "frames": frames,
    }
    out.mkdir(parents=True, exist_ok=True)
    bundle = write_bundle(out / "bundle", doc, images)
    info = {
        "object": dataclasses.asdict(obj),
        "renderer": {"mitsuba_version": mi.__version__, "variant": variant, "spp": spp},
        "ground_reflectance": GROUND_REFLECTANCE,
        "gain": gain,
        "camera": dataclasses.asdict(camera),
    }

    def fill(tmp: Path) -> None:
        for key in ("height", "normals", "mask"):
            write_new_file(tmp / f"{key}.npy", npy_bytes(gt[key]))
        write_new_file(tmp / "scene.json", json.dumps(info, indent=1).encode())

    replace_dir_atomic(out / "gt", fill)
    return bundle, out / "gt"
