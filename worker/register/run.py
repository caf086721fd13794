"""Model directories → registered tablet: transforms, one-node-per-face GLB, merged surface,
fatcross plates and the report, as bytes ready to be written (no I/O here beyond reading)."""

from __future__ import annotations

import json
import time

import numpy as np
from scipy import ndimage

from worker.bundle import is_simulated
from worker.register.fatcross import FaceMaps
from worker.register.io import load_model_dir
from worker.register.merge import grid_mesh, merged_surface, scene_glb
from worker.register.plates import DEFAULT_LICENCE, PlateInfo, fatcross_files
from worker.register.refine import register_scans

__all__ = ["register_model_dirs"]

DEFAULT_PX_PER_MM = 600 / 25.4  # 600 dpi


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
    meshes = {
        c.label: grid_mesh(
            raw["height_um"], raw["mask"], raw["albedo"], pixel_size_um=raw["pixel_size_um"]
        )
        for c, raw in loaded
    }
    glb = scene_glb(meshes, dict(zip(labels, reg.transforms, strict=True)))
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
    files, fatcross_report = fatcross_files(
        merged.vertices,
        merged.faces,
        merged.visual.vertex_colors,
        merged.vertex_normals,
        faces,
        px_per_mm=px_per_mm,
        name=name,
        info=info,
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
        "fatcross": fatcross_report,
        "simulated": info.simulated,
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
