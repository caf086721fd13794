"""Model directories → registered tablet: transforms, one-node-per-face GLB, merged surface,
fatcross plates and the report, as bytes ready to be written (no I/O here beyond reading)."""

from __future__ import annotations

import json
import time

from worker.register.fatcross import (
    FATCROSS_VIEWS,
    add_scale_bar,
    compose_fatcross,
    curvature_shading,
    natural_colour,
    render_orthographic,
)
from worker.register.io import face_asset_dir, load_model_dir, png_bytes
from worker.register.merge import face_normal_map, grid_mesh, merged_surface, scene_glb
from worker.register.refine import register_scans

__all__ = ["face_files", "register_model_dirs", "whole_tablet_model"]

DEFAULT_PX_PER_MM = 600 / 25.4  # 600 dpi


def whole_tablet_model(loaded: list[tuple], transforms: list) -> dict[str, bytes]:
    """The whole tablet for the viewer: ``model.glb`` (one node per face, scan → tablet
    transform, image-grid TEXCOORD_0, albedo) and every face's maps (`face_files`).
    ``loaded``: `load_model_dir` results; ``transforms``: 4×4 scan → tablet (mm), same order."""
    meshes = {
        c.label: grid_mesh(
            raw["height_um"], raw["mask"], raw["albedo"], pixel_size_um=raw["pixel_size_um"]
        )
        for c, raw in loaded
    }
    labels = [c.label for c, _ in loaded]
    files = {"model.glb": scene_glb(meshes, dict(zip(labels, transforms, strict=True)))}
    for c, raw in loaded:
        files.update(face_files(c.label, raw))
    return files


def face_files(label: str, raw: dict) -> dict[str, bytes]:
    """One face's full-resolution maps for the whole tablet, on its own image grid (the GLB
    node of that face carries the image-grid TEXCOORD_0): ``faces/<label>/normals.png``
    (scan-frame normals with the blending weight in alpha, `face_normal_map`) and the face
    model's shading maps (curvature, accessibility) as they are. The albedo is the node's
    baseColorTexture in model.glb."""
    prefix = face_asset_dir(label)
    rgba = face_normal_map(raw["normals"], raw["mask"], pixel_size_um=raw["pixel_size_um"])
    out = {f"{prefix}/normals.png": _png(rgba)}
    for name, data in raw.get("shading_maps", {}).items():
        out[f"{prefix}/{name}"] = data
    return out


def _png(image) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def register_model_dirs(
    model_dirs: list[str], *, px_per_mm: float = DEFAULT_PX_PER_MM, name: str = "tablet"
) -> tuple[dict[str, bytes], dict]:
    """Register the scans of ``model_dirs``; returns (files by name, report)."""
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
    colour, curvature = {}, {}
    for suffix, rot in FATCROSS_VIEWS.items():
        r = render_orthographic(
            merged.vertices,
            merged.faces,
            merged.visual.vertex_colors,
            merged.vertex_normals,
            rot,
            px_per_mm=px_per_mm,
        )
        colour[suffix] = natural_colour(r)
        curvature[suffix] = curvature_shading(r, px_per_mm=px_per_mm)
    gap = max(4, int(round(1.5 * px_per_mm)))
    for kind, images in (("", colour), ("_curvature", curvature)):
        for suffix, img in images.items():
            files[f"fatcross/{name}{kind}_{suffix}.png"] = png_bytes(
                add_scale_bar(img, px_per_mm=px_per_mm),
                px_per_mm=px_per_mm,
                description=f"{name} {suffix} {kind.strip('_') or 'colour'}, orthographic",
            )
        files[f"fatcross/{name}{kind}.png"] = png_bytes(
            add_scale_bar(compose_fatcross(images, gap_px=gap), px_per_mm=px_per_mm),
            px_per_mm=px_per_mm,
            description=f"{name} fatcross {kind.strip('_') or 'colour'}",
        )
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
        "fatcross": {"px_per_mm": round(px_per_mm, 4), "dpi": round(px_per_mm * 25.4, 1)},
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
    }
    files["transforms.json"] = json.dumps(transforms, indent=1).encode()
    files["merged.ply"] = merged.export(file_type="ply")
    files["tablet.glb"] = glb
    files["report.json"] = json.dumps(report, indent=1).encode()
    return files, report
