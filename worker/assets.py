"""Derived assets of a model directory, for the viewer and the library's result grid.

``derive_assets(model_dir)`` adds, next to the files of SCAN_BUNDLE.md (all image-grid
textures, docs/architecture.md):

- ``thumbnail.png``: the albedo lit by a raking light from the top left, RGBA (alpha = mask),
  at most 512 px on its long side;
- ``curvature.png`` (fine scale) and ``curvature_coarse.png``: signed mean curvature, grey
  128 = 0 (``worker.recon.shading_maps``);
- ``accessibility.png``: horizon-based ambient occlusion, 0 = enclosed … 255 = open;
- ``normals.png`` if the pipeline did not write it;
- ``shading.json``: the scales and encodings of the maps above;
- ``trust.png``, ``trust.json`` and ``uncertainty_um.npy``: where the heights rest on what,
  and how far to trust them (``worker.trust``), from ``quality/*.npy``.

Each file is written to a temporary name, fsynced and renamed: a crash leaves whole files.
Existing assets are rewritten identically (the maps are deterministic), so running this
twice is harmless.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from worker.durable import write_file_atomic
from worker.recon.shading_maps import (
    accessibility,
    encode_signed8,
    encode_unit8,
    mean_curvature_per_um,
    normals_rgb8,
    robust_scale,
)
from worker.trust_assets import TRUST_ASSETS, trust_assets

THUMBNAIL_MAX_PX = 512
CURVATURE_SCALES_UM = {"curvature.png": 200.0, "curvature_coarse.png": 1000.0}
ACCESSIBILITY_RADIUS_UM = 3000.0
MIN_SCALE_PX = 1.0
MIN_RADIUS_PX = 6.0
ASSET_NAMES = (
    "thumbnail.png",
    *CURVATURE_SCALES_UM,
    "accessibility.png",
    "normals.png",
    "shading.json",
    *TRUST_ASSETS,
)


class AssetError(ValueError):
    """The model directory lacks what the derived assets are made from."""


def _png_bytes(image: np.ndarray, name: str) -> bytes:
    img = image
    if image.ndim == 3:  # OpenCV wants BGR(A)
        img = image[..., [2, 1, 0, 3]] if image.shape[-1] == 4 else image[..., ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise OSError(f"{name}: PNG encoding failed")
    return buf.tobytes()


def _read_rgb(path: Path) -> np.ndarray | None:
    if not path.is_file():
        return None
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if img is None else img[..., ::-1]


def thumbnail_rgba(
    albedo_srgb8: np.ndarray | None, normals: np.ndarray, mask: np.ndarray
) -> np.ndarray:
    """(h, w, 4) uint8: albedo (grey clay if none) × (0.35 + 0.65·max(0, n·l)), alpha = mask,
    downsized (area average) so the long side is at most THUMBNAIL_MAX_PX."""
    # A light from the top-left at 45° elevation: l = (sinθ sinφ, sinθ cosφ, −cosθ), φ=225°.
    theta, phi = np.deg2rad(45.0), np.deg2rad(225.0)
    light = np.array([np.sin(theta) * np.sin(phi), np.sin(theta) * np.cos(phi), -np.cos(theta)])
    n = np.where(np.isfinite(normals), normals, np.array([0.0, 0.0, -1.0]))
    shade = 0.35 + 0.65 * np.clip(n @ light, 0.0, 1.0)
    base = (
        albedo_srgb8.astype(np.float64)
        if albedo_srgb8 is not None
        else np.full((*mask.shape, 3), 180.0)
    )
    rgb = np.clip(base * shade[..., None], 0, 255)
    rgba = np.concatenate([rgb, 255.0 * mask[..., None]], axis=-1).astype(np.float32)
    h, w = mask.shape
    factor = THUMBNAIL_MAX_PX / max(h, w)
    if factor < 1:
        size = (max(1, round(w * factor)), max(1, round(h * factor)))
        rgba = cv2.resize(rgba, size, interpolation=cv2.INTER_AREA)
    return np.clip(np.rint(rgba), 0, 255).astype(np.uint8)


def derive_assets(model_dir: str | os.PathLike) -> list[str]:
    """Write the derived assets into ``model_dir``; returns the names written."""
    model_dir = Path(model_dir)
    try:
        height_um = np.load(model_dir / "height.npy", allow_pickle=False)
        normals = np.load(model_dir / "normals.npy", allow_pickle=False)
        report = json.loads((model_dir / "report.json").read_text(encoding="utf-8"))
        pixel_size_um = float(report["pixel_size_um"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise AssetError(f"model directory {model_dir}: {exc}") from None
    mask = np.isfinite(height_um)
    if not mask.any():
        raise AssetError(f"model directory {model_dir}: height.npy has no finite value")
    written: list[str] = []

    def put(name: str, data: bytes) -> None:
        write_file_atomic(model_dir / name, data)
        written.append(name)

    albedo = _read_rgb(model_dir / "albedo.png")
    put("thumbnail.png", _png_bytes(thumbnail_rgba(albedo, normals, mask), "thumbnail.png"))

    meta: dict = {"curvature": {}, "accessibility": {}}
    for name, scale_um in CURVATURE_SCALES_UM.items():
        scale_um = max(scale_um, MIN_SCALE_PX * pixel_size_um)
        curv = mean_curvature_per_um(height_um, pixel_size_um=pixel_size_um, scale_um=scale_um)
        display = robust_scale(curv)
        put(name, _png_bytes(encode_signed8(curv, scale=display), name))
        meta["curvature"][name] = {
            "smoothing_sigma_um": scale_um,
            "encoding": "grey = 128 + 127.5·tanh(H / scale_per_um), H mean curvature in 1/µm",
            "scale_per_um": display,
        }

    radius_um = max(ACCESSIBILITY_RADIUS_UM, MIN_RADIUS_PX * pixel_size_um)
    acc = accessibility(height_um, pixel_size_um=pixel_size_um, radius_um=radius_um)
    put("accessibility.png", _png_bytes(encode_unit8(acc), "accessibility.png"))
    meta["accessibility"] = {"radius_um": radius_um, "encoding": "grey = 255·accessibility"}

    if not (model_dir / "normals.png").is_file():
        put("normals.png", _png_bytes(normals_rgb8(normals), "normals.png"))
    put("shading.json", json.dumps(meta, indent=1).encode("utf-8"))
    for name, data in trust_assets(model_dir, height_um, report).items():
        put(name, data)
    return written
