"""Writer of the model directory (SCAN_BUNDLE.md, "Reconstruction output").

Files: height.npy, normals.npy, albedo.png, mask.png, mesh.ply, model.glb, report.json, plus
normals.png (object-space normals, RGB = (n + 1)/2, for the viewer) and quality/*.npy.
Everything is written into a temporary directory next to OUTDIR, each file fsynced, and the
directory renamed into place: OUTDIR holds either the whole model or what it held before.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from worker.durable import npy_bytes, replace_dir_atomic, write_new_file
from worker.recon.glb import glb_bytes
from worker.recon.mesh import grid_mesh, ply_bytes

__all__ = ["ModelArrays", "albedo_png_bytes", "write_model_dir", "write_model_dir_timed"]


class ModelArrays:
    """What a model directory holds, as arrays (shapes in the SCAN_BUNDLE.md table)."""

    def __init__(
        self,
        *,
        height_um: np.ndarray,
        normals: np.ndarray,
        albedo_srgb8: np.ndarray,
        mask: np.ndarray,
        pixel_size_um: float,
        quality: Mapping[str, np.ndarray],
        albedo_png: bytes | None = None,
    ):
        self.height_um = height_um
        self.normals = normals
        self.albedo_srgb8 = albedo_srgb8
        self.mask = mask
        self.pixel_size_um = pixel_size_um
        self.quality = dict(quality)
        # albedo.png as `albedo_png_bytes(albedo_srgb8)` gives it, when the caller encoded
        # it already (beside other work); encoded by the writer otherwise.
        self.albedo_png = albedo_png


def _png_bytes(name: str, image: np.ndarray) -> bytes:
    """PNG encoding of the grey (H, W) or RGB (H, W, 3) uint8 image of file `name`."""
    img = image[..., ::-1] if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise OSError(f"{name}: PNG encoding failed")
    return buf.tobytes()


def albedo_png_bytes(albedo_srgb8: np.ndarray) -> bytes:
    """albedo.png's bytes for the (H, W, 3) sRGB albedo (`ModelArrays.albedo_png`)."""
    return _png_bytes("albedo.png", np.asarray(albedo_srgb8, np.uint8))


def write_model_dir_timed(
    out_dir: str | os.PathLike,
    model: ModelArrays,
    report: dict,
    *,
    timings: dict[str, float],
    started_s: float,
    progress: Callable[[str, float], None],
) -> dict:
    """`write_model_dir` with the time spent writing and the whole run's (from
    `started_s`, a `time.perf_counter()` value) added to `timings` and to report.json's
    `timings_s`; progress reports "write" then "done"."""
    t0 = time.perf_counter()
    progress("write", 0.90)

    def finish(rep: dict) -> dict:
        timings["write"] = time.perf_counter() - t0
        timings["total"] = time.perf_counter() - started_s
        return {**rep, "timings_s": dict(timings)}

    report = write_model_dir(out_dir, model, report, finish_report=finish)
    progress("done", 1.0)
    return report


def write_model_dir(
    out_dir: str | os.PathLike,
    model: ModelArrays,
    report: dict,
    *,
    max_glb_triangles: int = 200_000,
    finish_report: Callable[[dict], dict] | None = None,
) -> dict:
    """Write the model directory atomically; returns the report (with mesh figures added).

    `finish_report(report) -> report` is called just before report.json is written (the
    last file), e.g. to record the time spent writing. An existing OUTDIR is replaced only
    once the new one is complete.
    """
    written: dict = {}

    def fill(tmp: Path) -> None:
        written["report"] = _fill(tmp, model, report, max_glb_triangles, finish_report)

    replace_dir_atomic(out_dir, fill)
    report = written["report"]
    return report


def _fill(tmp: Path, model: ModelArrays, report: dict, max_glb_triangles: int, finish) -> dict:
    m = np.asarray(model.mask, bool)
    # Fresh arrays from np.where: cast only if they are not float32 already (the GLB and
    # mesh jobs start once they are there).
    h = np.where(m, model.height_um, np.nan).astype(np.float32, copy=False)
    n = np.where(m[..., None], model.normals, np.nan).astype(np.float32, copy=False)
    ok = m & np.isfinite(h)
    albedo = np.asarray(model.albedo_srgb8, np.uint8)
    (tmp / "quality").mkdir()
    with ThreadPoolExecutor(max_workers=2) as pool, ThreadPoolExecutor(max_workers=1) as disk:
        # Each file goes to disk (write, fsync) in its own thread while the next is encoded:
        # the fsyncs wait on the device, not on a core.
        saved = []

        def save(name: str, data: bytes) -> None:
            saved.append(disk.submit(write_new_file, tmp / name, data))

        # albedo.png and the GLB's base colour texture are the same PNG: encoded once.
        albedo_png = model.albedo_png
        if albedo_png is None:
            albedo_png = albedo_png_bytes(albedo)
        # model.glb (full-resolution textures) and mesh.ply, the largest parts, are built
        # beside the images and grids.
        glb_job = pool.submit(
            glb_bytes,
            h,
            ok,
            n,
            albedo,
            pixel_size_um=model.pixel_size_um,
            max_triangles=max_glb_triangles,
            albedo_png=albedo_png,
        )
        mesh_job = pool.submit(_write_mesh, save, model.pixel_size_um, h, n, ok, albedo)
        save("albedo.png", albedo_png)
        _write_grids(save, m, h, n)
        for name, arr in model.quality.items():
            save(f"quality/{name}.npy", npy_bytes(np.asarray(arr)))
        mesh = mesh_job.result()
        glb, info = glb_job.result()
        save("model.glb", glb)
        for job in saved:
            job.result()
    report = dict(report)
    report["mesh"] = {
        "ply_vertices": len(mesh.vertices_mm),
        "ply_triangles": len(mesh.faces),
        "glb_vertices": info["vertices"],
        "glb_triangles": info["triangles"],
        "glb_grid_step_px": info["step"],
    }
    if finish is not None:
        report = finish(report)
    # Last, once every other file is on disk.
    write_new_file(tmp / "report.json", json.dumps(report, indent=1, allow_nan=False).encode())
    return report


def _write_grids(save: Callable[[str, bytes], None], mask, h, n) -> None:
    """height.npy, normals.npy, mask.png and normals.png, each handed to `save(name, bytes)`."""
    save("height.npy", npy_bytes(h))
    save("normals.npy", npy_bytes(n))
    save("mask.png", _png_bytes("mask.png", np.where(mask, 255, 0).astype(np.uint8)))
    rgb = np.where(np.isfinite(n), np.clip(np.rint((n + 1.0) * 127.5), 0, 255), 0).astype(np.uint8)
    save("normals.png", _png_bytes("normals.png", rgb))


def _write_mesh(save: Callable[[str, bytes], None], pixel_size_um: float, h, n, ok, albedo):
    """mesh.ply, handed to `save`; returns the full-resolution mesh."""
    mesh = grid_mesh(h, ok, pixel_size_um=pixel_size_um)
    vn = n[mesh.rows, mesh.cols]
    vn = np.where(np.isfinite(vn), vn, np.array([0, 0, -1], np.float32))
    save(
        "mesh.ply",
        ply_bytes(
            mesh.vertices_mm, mesh.faces, normals=vn, colors_rgb8=albedo[mesh.rows, mesh.cols]
        ),
    )
    return mesh
