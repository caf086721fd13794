"""Model directories → registered tablet: transforms, one-node-per-face GLB, merged surface,
fatcross plates and the report, as bytes ready to be written (no I/O here beyond reading)."""

from __future__ import annotations

import io
import json
import time

import numpy as np
from scipy import ndimage

from worker.bundle import is_simulated
from worker.durable import npy_bytes
from worker.register.blend import FaceGrid, blend_faces, face_weight
from worker.register.fatcross import FaceMaps
from worker.register.io import face_asset_dir, load_model_dir
from worker.register.merge import face_normal_map, grid_mesh, merged_surface, scene_glb
from worker.register.plates import DEFAULT_LICENCE, PlateInfo, fatcross_files
from worker.register.refine import register_scans
from worker.trust_assets import QUALITY_INPUTS, trust_files, trust_maps, trust_scales_um

__all__ = ["blend_loaded", "face_files", "register_model_dirs", "whole_tablet_model"]

DEFAULT_PX_PER_MM = 600 / 25.4  # 600 dpi


def whole_tablet_model(loaded: list[tuple], transforms: list) -> dict[str, bytes]:
    """The whole tablet for the viewer: ``model.glb`` (one node per face, scan → tablet
    transform, image-grid TEXCOORD_0, albedo) and every face's maps (`face_files`), with the
    normals and albedo blended across the seams where faces overlap (`blend_faces`).
    ``loaded``: `load_model_dir` results; ``transforms``: 4×4 scan → tablet (mm), same order."""
    blended = blend_loaded(loaded, transforms)
    meshes = {
        c.label: grid_mesh(
            raw["height_um"], raw["mask"], albedo, pixel_size_um=raw["pixel_size_um"]
        )
        for (c, raw), (_, albedo) in zip(loaded, blended, strict=True)
    }
    labels = [c.label for c, _ in loaded]
    files = {"model.glb": scene_glb(meshes, dict(zip(labels, transforms, strict=True)))}
    for (c, raw), (normals, _) in zip(loaded, blended, strict=True):
        files.update(face_files(c.label, raw, normals=normals))
    files.update(faces_trust_files(loaded))
    return files


def faces_trust_files(loaded: list[tuple]) -> dict[str, bytes]:
    """Each face's trust assets (worker/trust_assets.py: ``trust.png``, ``trust.json``,
    ``uncertainty_um.npy``) under ``faces/<label>/``, from its own quality maps, heights and
    normals as the face model had them (not the blended normals: σ_h is the face's own
    measurement). One pair of legend tops for every face (the largest of the faces' own), so
    one legend in µm reads the whole tablet."""
    maps = []
    for _, raw in loaded:
        quality = {
            name: _npy(raw.get("quality_maps", {}).get(f"{name}.npy")) for name in QUALITY_INPUTS
        }
        m = trust_maps(
            raw["height_um"], quality, normals=raw["normals"], pixel_size_um=raw["pixel_size_um"]
        )
        maps.append((quality, m))
    if not maps:
        return {}
    tops = [trust_scales_um(*m) for _, m in maps]
    scales = (max(t[0] for t in tops), max(t[1] for t in tops))
    out = {}
    for (c, raw), (quality, m) in zip(loaded, maps, strict=True):
        prefix = face_asset_dir(c.label)
        files = trust_files(
            raw["height_um"],
            quality,
            normals=raw["normals"],
            pixel_size_um=raw["pixel_size_um"],
            refinements=raw.get("refinements", {}),
            scales_um=scales,
            maps=m,
        )
        out.update({f"{prefix}/{name}": data for name, data in files.items()})
    return out


def _npy(data: bytes | None) -> np.ndarray | None:
    """A .npy file's array, or None when absent or unreadable (the trust map says less)."""
    if data is None:
        return None
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except (OSError, ValueError):
        return None


def blend_loaded(loaded: list[tuple], transforms: list) -> list[tuple]:
    """Per face, (normals, albedo as uint8 RGB or None) blended across the seams: the
    stored albedo is blended in its own (sRGB-encoded) scale, the same for every face."""
    faces = [
        FaceGrid(
            raw["height_um"],
            raw["normals"],
            raw["mask"],
            None if raw["albedo"] is None else _rgb8(raw["albedo"]).astype(np.float64),
            raw["pixel_size_um"],
            np.asarray(t, np.float64),
        )
        for (_, raw), t in zip(loaded, transforms, strict=True)
    ]
    out = []
    for normals, albedo in blend_faces(faces):
        rgb8 = None if albedo is None else np.clip(np.rint(albedo), 0, 255).astype(np.uint8)
        out.append((normals, rgb8))
    return out


def face_files(label: str, raw: dict, *, normals: np.ndarray | None = None) -> dict[str, bytes]:
    """One face's full-resolution maps for the whole tablet, on its own image grid (the GLB
    node of that face carries the image-grid TEXCOORD_0 and the scan → tablet transform):
    ``faces/<label>/normals.png`` (``normals``, default the face's own, in its scan frame,
    with the face's own quality weight in alpha, `face_normal_map`), the face model's shading
    maps (curvature, accessibility), its heights (``height.npy``), its quality maps
    (``quality/*.npy``; the trust assets made from them are `faces_trust_files`'), photographs
    (``photos/index.json`` and JPEGs) and measured gloss (``gloss.png``/``gloss.json``) as they
    are.
    The albedo is the node's baseColorTexture in model.glb."""
    prefix = face_asset_dir(label)
    own = face_weight(raw["normals"], raw["mask"], pixel_size_um=raw["pixel_size_um"])
    rgba = face_normal_map(
        raw["normals"] if normals is None else normals,
        raw["mask"],
        pixel_size_um=raw["pixel_size_um"],
        weight=own,
    )
    out = {f"{prefix}/normals.png": _png(rgba)}
    # The face's full-resolution heights (its own grid, µm, NaN off the tablet): what the
    # viewer's profiles and sections of the whole tablet are cut from, as on the face model.
    out[f"{prefix}/height.npy"] = npy_bytes(np.asarray(raw["height_um"], np.float32))
    for name, data in raw.get("shading_maps", {}).items():
        out[f"{prefix}/{name}"] = data
    for name, data in raw.get("quality_maps", {}).items():
        out[f"{prefix}/quality/{name}"] = data
    for name, data in raw.get("photo_files", {}).items():
        out[f"{prefix}/{name}"] = data
    return out


def _png(image) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def register_model_dirs(
    model_dirs: list[str],
    *,
    px_per_mm: float = DEFAULT_PX_PER_MM,
    name: str = "tablet",
    designation: str | None = None,
    licence: str = DEFAULT_LICENCE,
) -> tuple[dict[str, bytes], dict]:
    """Register the scans of ``model_dirs``; returns (files by name, report). ``name`` is the
    plates' file-name stem, ``designation`` their title (default ``name``)."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    loaded = [load_model_dir(d) for d in model_dirs]
    scans = [c for c, _ in loaded]
    labels = [c.label for c in scans]
    if len(set(labels)) != len(labels):
        raise ValueError(f"model directories: two scans share a label (scan.id or face): {labels}")
    timings["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    reg = register_scans(scans)
    timings["register"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    merged = merged_surface(scans, reg.transforms)
    files = whole_tablet_model(loaded, reg.transforms)
    glb = files.pop("model.glb")
    timings["merge"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # The plates shade with each scan's own normals, steep wedge walls included (the
    # registration left those out); only the rim, seen at a grazing angle, is dropped.
    faces = [
        FaceMaps(
            t,
            raw["normals"],
            None if raw["albedo"] is None else _rgb8(raw["albedo"]),
            ndimage.binary_erosion(raw["mask"], iterations=2),
            raw["height_um"],
            raw["pixel_size_um"],
        )
        for (_, raw), t in zip(loaded, reg.transforms, strict=True)
    ]
    info = PlateInfo(
        designation or name,
        licence=licence,
        simulated=any(is_simulated(raw.get("tablet") or {}) for _, raw in loaded),
    )
    plate_files, fatcross_report = fatcross_files(
        merged.vertices,
        merged.faces,
        merged.visual.vertex_colors,
        merged.vertex_normals,
        faces,
        px_per_mm=px_per_mm,
        name=name,
        info=info,
    )
    files.update(plate_files)
    timings["fatcross"] = time.perf_counter() - t0
    transforms = {
        "convention": "X_tablet = rotation @ X_scan + translation_mm; scan frame as in "
        "SCAN_BUNDLE.md in mm ((c·s, r·s, -h)/1000); tablet frame: obverse toward -z",
        "scans": {
            lab: {
                "model_dir": str(d),
                "rotation": t[:3, :3].tolist(),
                "translation_mm": t[:3, 3].tolist(),
                "init": how,
            }
            for lab, d, t, how in zip(labels, model_dirs, reg.transforms, reg.init, strict=True)
        },
    }
    report = {
        "scans": labels,
        "pairs": [p.__dict__ for p in reg.pairs],
        "moved_by_icp": reg.restarts,
        "merged": {"vertices": len(merged.vertices), "triangles": len(merged.faces)},
        "fatcross": fatcross_report,
        "simulated": info.simulated,
        # What each face carries into the whole tablet (docs/registration.md, "Faces").
        "faces": {
            c.label: {
                "assets": face_asset_dir(c.label),
                "face": c.face,
                "pixel_size_um": raw["pixel_size_um"],
                "quality_maps": sorted(raw.get("quality_maps", {})),
                "trust": f"{face_asset_dir(c.label)}/trust.json" in files,
                "photos": "photos/index.json" in raw.get("photo_files", {}),
                "gloss": "gloss.png" in raw.get("photo_files", {}),
            }
            for c, raw in loaded
        },
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
    }
    files["transforms.json"] = json.dumps(transforms, indent=1).encode()
    files["merged.ply"] = merged.export(file_type="ply")
    files["tablet.glb"] = glb
    files["report.json"] = json.dumps(report, indent=1).encode()
    return files, report


def _rgb8(albedo) -> np.ndarray:
    a = np.asarray(albedo)
    return np.repeat(a[..., None], 3, -1) if a.ndim == 2 else a[..., :3]
