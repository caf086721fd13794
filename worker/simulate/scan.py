"""Simulate whole scans: render every frame, write the bundle and the ground truth beside it.

Layout (docs/architecture.md, "Simulator"): ``OUT/bundle/`` (or ``OUT/bundle.zip``) and
``OUT/gt/{height,normals,albedo,mask}.npy, wedges.json``; for ``face="all"`` one such pair
per face under ``OUT/<face>/`` plus ``OUT/poses.json`` and ``OUT/tablet.ply``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from worker.bundle import write_bundle
from worker.durable import npy_bytes, replace_dir_atomic, write_file_atomic, write_new_file
from worker.simulate.acquisition import (
    PAPER_PIXEL_UM,
    PRESETS,
    frame_file,
    frame_size_for,
    manifest,
    pixel_size_for,
    plan_frames,
)
from worker.simulate.meshview import MeshTablet, load_mesh, mesh_points, render_mesh_view
from worker.simulate.noise import NoiseModel, noise_model
from worker.simulate.physics import IDEAL, Physics, physics_to_dict, resolve_physics
from worker.simulate.rig import Rig, render_frame
from worker.simulate.support import scale_albedo, with_support
from worker.simulate.tablet import FACE_POSES, FACES, Tablet, check_size_mm, make_tablet
from worker.simulate.view import View, cast_grid, render_view

__all__ = [
    "SimulationResult",
    "parse_size",
    "point_truth",
    "scan_rig",
    "scene",
    "simulate_scan",
    "view_extent_um",
    "wedge_records",
]


@dataclass(frozen=True)
class SimulationResult:
    """Where things were written; ``views`` maps face → View (kept for callers' checks)."""

    out_dir: Path
    bundles: dict[str, Path]
    gt_dirs: dict[str, Path]
    views: dict[str, View]
    n_frames: int


def parse_size(text: str) -> tuple[int, int]:
    """'512x384' → (512, 384); ValueError naming the argument otherwise."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"size: expected WIDTHxHEIGHT such as 512x384, got {text!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ValueError(f"size: width and height must be 16..8192, got {text!r}")
    return w, h


def wedge_records(tablet: Tablet | MeshTablet, view: View) -> list[dict]:
    """The wedges that face the camera and lie in the frame, in view coordinates.

    Each: face, centre/bottom/rim as {row, col, height_um}, direction_deg in the image
    (0° = +x/right, 90° = +y/down), width_um, depth_um (apex below the tangent plane),
    depth_view_um = mean rim height - bottom height in this view.
    """
    s = view.pixel_size_um

    def to_view(p: np.ndarray) -> dict:
        q = view.pose @ p + view.translation_um
        return {"row": float(q[1] / s), "col": float(q[0] / s), "height_um": float(-q[2])}

    out = []
    for i, w in enumerate(getattr(tablet, "wedges", ())):
        if (view.pose @ w.normal)[2] > -0.5:
            continue
        bottom = to_view(w.apex_um)
        rim = [to_view(p) for p in w.rim_um]
        points = [bottom, *rim]
        if not all(
            0 <= p["row"] <= view.height - 1 and 0 <= p["col"] <= view.width - 1 for p in points
        ):
            continue
        d = view.pose @ w.direction
        out.append(
            {
                "id": i,
                "face": w.face,
                "centre": to_view(w.centre_um),
                "direction_deg": float(np.degrees(np.arctan2(d[1], d[0]))),
                "width_um": w.width_um,
                "depth_um": w.depth_um,
                "bottom": bottom,
                "rim": rim,
                "depth_view_um": float(
                    np.mean([p["height_um"] for p in rim]) - bottom["height_um"]
                ),
                "has_tail": w.tail_end_um is not None,
            }
        )
    return out


SIMULATOR = {"name": "worker.simulate", "version": 2}  # version: bump when frames change


def point_truth(
    tablet: Tablet | MeshTablet, view: View, *, albedo_scale: float = 1.0
) -> dict[str, np.ndarray]:
    """Ground truth as SCAN_BUNDLE.md defines the output: point samples at pixel centres.

    One ray per pixel through p = (c·s, r·s), in the view's frame (its pose and
    translation): height (H, W) µm, normals (H, W, 3) (the surface's own normal there),
    albedo (H, W, 3) linear RGB (times ``albedo_scale``, clipped to 0.95 as in the frames),
    mask (H, W) as ``View.ground_truth`` (every sample of the pixel on the tablet); NaN
    outside the mask.
    """
    s = view.pixel_size_um
    xs, ys = np.arange(view.width) * s, np.arange(view.height) * s
    t_xy = np.array([view.translation_um[0], view.translation_um[1], 0.0])
    if isinstance(tablet, MeshTablet):
        z, normals, albedo = mesh_points(tablet, view.pose, xs, ys, t_xy, s)
        albedo = np.array(albedo, np.float64)
    else:
        z, normals = cast_grid(tablet, view.pose, xs, ys, t_xy, s)
    height = -view.translation_um[2] - z
    mask = view.ground_truth()["mask"] & np.isfinite(z)
    if not isinstance(tablet, MeshTablet):
        gx, gy = np.meshgrid(xs, ys)
        pts = np.stack([gx[mask], gy[mask], -height[mask]], -1)
        albedo = np.zeros((*z.shape, 3))
        albedo[mask] = tablet.albedo((pts - view.translation_um) @ view.pose)
    if albedo_scale != 1.0:
        albedo = np.clip(albedo * np.float32(albedo_scale), 0.0, 0.95)
    out = {"height": height, "normals": np.array(normals, np.float64), "albedo": albedo}
    for a in out.values():
        a[~mask] = np.nan
    out = {k: v.astype(np.float32) for k, v in out.items()}
    out["mask"] = mask
    return out


def write_gt_dir(
    gt_dir: Path, gt: dict, view: View, tablet: Tablet | MeshTablet, physics_doc: dict
) -> None:
    """The ground-truth folder, atomically, the same for every renderer: `gt`'s point-sampled
    height, normals, albedo and mask, the pixel-mean height (height_area.npy: the box mean of
    each pixel's samples), the wedges and `physics_doc` as physics.json."""

    def fill(tmp: Path) -> None:
        for name in ("height", "normals", "albedo", "mask"):
            write_new_file(tmp / f"{name}.npy", npy_bytes(gt[name]))
        write_new_file(tmp / "height_area.npy", npy_bytes(view.ground_truth()["height"]))
        text = json.dumps({"wedges": wedge_records(tablet, view)}, indent=1)
        write_new_file(tmp / "wedges.json", text.encode())
        write_new_file(tmp / "physics.json", json.dumps(physics_doc, indent=1).encode())

    replace_dir_atomic(gt_dir, fill)


def _write_gt(
    gt_dir: Path, view: View, tablet: Tablet | MeshTablet, physics: Physics, physics_seed
) -> None:
    gt = point_truth(tablet, view, albedo_scale=physics.albedo_scale)
    doc = {
        "simulator": SIMULATOR,
        "physics_seed": physics_seed,
        "physics": physics_to_dict(physics),
    }
    write_gt_dir(gt_dir, gt, view, tablet, doc)


def _check_fringe_range(view: View, preset_polar_deg: float, coarsest_um: float) -> None:
    h = view.height_ss_um[view.tablet_ss]
    need = 2 * np.tan(np.radians(preset_polar_deg)) * float(np.max(np.abs(h)))
    if coarsest_um <= need:
        raise ValueError(
            f"coarsest fringe period {coarsest_um:.0f} µm does not exceed 2·tanθ·max|h| = {need:.0f} µm"
        )


def view_extent_um(tablet: Tablet | MeshTablet, pose: np.ndarray) -> tuple[float, float]:
    """The tablet's extent (x, y) µm across the view of rotation ``pose`` (tablet→view): the
    body's bounding box turned into the view (a mesh: its vertices)."""
    pose = np.asarray(pose, float)
    if isinstance(tablet, MeshTablet):
        v = tablet.vertices_um @ pose.T
        span = v.max(axis=0) - v.min(axis=0)
        return float(span[0]), float(span[1])
    half = np.abs(pose) @ tablet.pillow.bounding_half_um
    return float(2 * half[0]), float(2 * half[1])


def face_grid(
    tablet: Tablet | MeshTablet,
    pose: np.ndarray,
    *,
    size: tuple[int, int] | None,
    pixel_size_um: float | None,
    preset: str,
) -> tuple[tuple[int, int], float]:
    """Frame size (px) and pixel size (µm) of one view.

    ``size`` given: that frame, at ``pixel_size_um`` or else the pixel that keeps the paper's
    field (34.3 × 27.4 mm) in it. ``pixel_size_um`` alone: the frame follows the tablet seen
    through ``pose`` (``frame_size_for``). Neither: the preset's frame over the paper's field.
    """
    if size is not None:
        return size, float(pixel_size_um or pixel_size_for(*size))
    if pixel_size_um is None:
        size = (PRESETS[preset].width, PRESETS[preset].height)
        return size, pixel_size_for(*size)
    return frame_size_for(view_extent_um(tablet, pose), pixel_size_um), float(pixel_size_um)


def scan_rig(
    seed: int,
    width: int,
    height: int,
    pixel_size_um: float,
    noise: NoiseModel,
    physics: Physics = IDEAL,
) -> Rig:
    """The instrument of a simulated scan (the same for every face of a seed)."""
    return Rig(
        seed,
        width * pixel_size_um,
        height * pixel_size_um,
        irradiance_variation=physics.camera(noise).irradiance_variation,
        physics=physics,
    )


def scene(
    tablet: Tablet | MeshTablet,
    pose: np.ndarray,
    *,
    seed: int,
    size: tuple[int, int],
    preset: str = "quick",
    noise: NoiseModel,
    physics: Physics = IDEAL,
    pixel_size_um: float | None = None,
) -> tuple[View, Rig]:
    """The view and instrument that ``simulate_scan`` uses for one pose, for callers that
    render frames themselves (the rig agent's simulated camera: ``render_frame(view, frame,
    noise, rng, rig=rig)``). ``physics`` adds the support and clay albedo to the view and
    rides in the rig (``render_frame`` applies its camera overrides to ``noise``).
    ``pixel_size_um``: default, the pixel that keeps the paper's field in ``size``."""
    width, height = size
    pixel = float(pixel_size_um or pixel_size_for(width, height))
    render = render_mesh_view if isinstance(tablet, MeshTablet) else render_view
    view = render(
        tablet,
        pose,
        width=width,
        height=height,
        pixel_size_um=pixel,
        supersample=PRESETS[preset].supersample,
    )
    view = with_support(scale_albedo(view, physics.albedo_scale), physics.support, seed)
    return view, scan_rig(seed, width, height, pixel, noise, physics)


def _simulate_face(
    tablet: Tablet | MeshTablet,
    face: str,
    face_dir: Path,
    *,
    seed: int,
    size: tuple[int, int],
    preset_name: str,
    noise: NoiseModel,
    as_zip: bool,
    progress: bool,
    pose: np.ndarray | None = None,
    physics: Physics = IDEAL,
    physics_seed: int | None = None,
    pixel_size_um: float | None = None,
    scan_suffix: str = "",
) -> tuple[Path, Path, View, int]:
    from tqdm import tqdm

    preset = PRESETS[preset_name]
    pose = FACE_POSES[face] if pose is None else pose
    size, pixel_um = face_grid(
        tablet, pose, size=size, pixel_size_um=pixel_size_um, preset=preset_name
    )
    width, height = size
    view, rig = scene(
        tablet,
        pose,
        seed=seed,
        size=size,
        preset=preset_name,
        noise=noise,
        physics=physics,
        pixel_size_um=pixel_um,
    )
    pixel = view.pixel_size_um
    camera = physics.camera(noise)
    frames = plan_frames(
        preset,
        width=width,
        height=height,
        pixel_size_um=pixel,
        noise=camera,
        rng=np.random.default_rng([seed, 0xE0]),
    )
    coarsest = min(  # the coarsest period of each azimuth must do; check the smallest of them
        max(f.period_um for f in frames if f.kind == "fringe" and f.azimuth_deg == az)
        for az in {f.azimuth_deg for f in frames if f.kind == "fringe"}
    )
    _check_fringe_range(view, preset.polar_deg, coarsest)
    files = [frame_file(f, i) for i, f in enumerate(frames)]
    face_id = [*FACES, "other"].index(face)
    images = {}
    for i, (frame, file) in enumerate(
        tqdm(
            list(zip(frames, files, strict=True)),
            desc=f"{face} frames",
            unit="frame",
            file=sys.stderr,
            disable=not progress,
        )
    ):
        rng = np.random.default_rng([seed, face_id, i])
        images[file] = render_frame(view, frame, camera, rng, rig=rig)
    view.cache.clear()  # shadows and fringe terms: hundreds of MB at the paper size
    doc = manifest(
        frames,
        files,
        face=face,
        pose=pose,
        seed=seed,
        width=width,
        height=height,
        pixel_size_um=pixel,
        noise=camera,
        polar_deg=preset.polar_deg,
        reflectance=rig.reflectance_reference,
        psf_sigma_px=physics.calibrated_psf_px(noise),
        physics_name=physics.name,
    )
    if scan_suffix:
        doc["scan"]["id"] += scan_suffix
    face_dir.mkdir(parents=True, exist_ok=True)
    bundle = face_dir / ("bundle.zip" if as_zip else "bundle")
    write_bundle(bundle, doc, images, as_zip=as_zip)
    gt_dir = face_dir / "gt"
    _write_gt(gt_dir, view, tablet, physics, physics_seed)
    return bundle, gt_dir, view, len(frames)


def simulate_scan(
    out_dir: str | os.PathLike,
    *,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    face: str = "obverse",
    preset: str = "quick",
    noise: str | NoiseModel = "default",
    as_zip: bool = False,
    progress: bool = False,
    mesh: str | os.PathLike | None = None,
    pose: np.ndarray | None = None,
    physics: str | Physics = "ideal",
    physics_seed: int | None = None,
    tablet_mm: tuple[float, float, float] | None = None,
    pixel_size_um: float | None = None,
) -> SimulationResult:
    """Simulate the scan of one face (or ``"all"`` six) of the synthetic tablet of ``seed``,
    or of the triangle mesh file ``mesh`` (mm, obverse toward -z; no wedges.json entries).

    ``physics``: a ``Physics``, a name in ``PHYSICS_VARIANTS`` or ``"random"`` (drawn from
    ``physics_seed``, default ``seed``); written to ``gt/physics.json``. A mesh keeps its
    own shape (the physics' ``shape`` is then recorded as ``standard``).

    ``pose`` (3×3 rotation tablet→view) replaces the face's standard pose, for oblique views;
    ``face`` then only labels the scan (``"other"`` is allowed).

    ``tablet_mm``: the synthetic tablet's outer width, height and thickness (mm; default
    28 × 22 × 12). With it, and no ``size``, each face's frame follows the tablet at
    ``pixel_size_um`` (default the paper's 26.8 µm): a small tablet gives small frames
    (``face_grid``), and the scan id ends in ``-t<W>x<H>x<T>mm``. ``pixel_size_um`` alone
    does the same for the standard tablet (or a mesh).

    Refuses (FileExistsError) to overwrite an existing bundle or gt folder.
    """
    if preset not in PRESETS:
        raise ValueError(f"preset: unknown {preset!r}; choose from {sorted(PRESETS)}")
    faces = FACES if face == "all" else (face,)
    labels = [*FACES, "other"] if pose is not None else list(FACES)
    if face != "all" and face not in labels:
        raise ValueError(f"face: unknown {face!r}; choose from {[*labels, 'all']}")
    if pose is not None:
        pose = np.asarray(pose, dtype=float)
        if face == "all":
            raise ValueError("pose: give one face (or 'other') with an explicit pose, not 'all'")
        if pose.shape != (3, 3) or not np.allclose(pose @ pose.T, np.eye(3), atol=1e-6):
            raise ValueError("pose: must be a 3×3 rotation matrix")
    model = noise if isinstance(noise, NoiseModel) else noise_model(noise)
    if physics_seed is None:
        physics_seed = seed
    elif isinstance(physics_seed, bool) or not isinstance(physics_seed, int) or physics_seed < 0:
        raise ValueError(f"physics_seed: must be an integer >= 0, got {physics_seed!r}")
    drawn = resolve_physics(physics, physics_seed)
    if mesh is not None and drawn.shape != "standard":
        drawn = dataclasses.replace(drawn, shape="standard")
    if pixel_size_um is not None and not (
        isinstance(pixel_size_um, int | float) and 1.0 <= pixel_size_um <= 2000.0
    ):
        raise ValueError(f"pixel size: must be 1..2000 µm, got {pixel_size_um!r}")
    scan_suffix = ""
    if tablet_mm is not None:
        if mesh is not None:
            raise ValueError("tablet size: a mesh has its own size; give one of them")
        check_size_mm(tablet_mm)
        scan_suffix = "-t{:g}x{:g}x{:g}mm".format(*tablet_mm)
        if size is None and pixel_size_um is None:
            pixel_size_um = PAPER_PIXEL_UM
    out = Path(out_dir)
    dirs = {f: (out / f if face == "all" else out) for f in faces}
    for d in dirs.values():
        for name in ("bundle", "bundle.zip", "gt"):
            if (d / name).exists():
                raise FileExistsError(f"out: {d / name} exists; choose an empty --out")
    if mesh is not None:
        tablet = load_mesh(mesh)
    else:
        tablet = make_tablet(seed, shape=drawn.shape, size_mm=tablet_mm)
    bundles, gts, views, n = {}, {}, {}, 0
    for f in faces:
        bundles[f], gts[f], views[f], k = _simulate_face(
            tablet,
            f,
            dirs[f],
            seed=seed,
            size=size,
            preset_name=preset,
            noise=model,
            as_zip=as_zip,
            progress=progress,
            pose=pose,
            physics=drawn,
            physics_seed=physics_seed,
            pixel_size_um=pixel_size_um,
            scan_suffix=scan_suffix,
        )
        n += k
    if face == "all":
        from worker.simulate.mesh import tablet_mesh

        poses = {
            f: {
                "rotation": views[f].pose.tolist(),
                "translation_um": views[f].translation_um.tolist(),
            }
            for f in faces
        }
        doc = {
            "convention": "X_view = rotation @ X_tablet + translation_um; view (x, y, z) = "
            "(c·s, r·s, -h) in µm; tablet.ply is in mm in the tablet frame",
            "poses": poses,
        }
        write_file_atomic(out / "poses.json", json.dumps(doc, indent=1).encode())
        if isinstance(tablet, MeshTablet):
            solid = trimesh.Trimesh(tablet.vertices_um / 1000.0, tablet.faces, process=False)
        else:
            solid = tablet_mesh(tablet)
        write_file_atomic(out / "tablet.ply", solid.export(file_type="ply"))
    return SimulationResult(out, bundles, gts, views, n)
