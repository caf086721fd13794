"""The trust assets of a model directory (I/O around ``worker.trust``), for the viewer.

- ``trust.png`` (RGBA, image grid): R = source class (``worker.trust.TRUST_CLASSES``),
  G = |fringe − final height| and B = σ_h, each 8-bit on a linear scale whose top (µm) is in
  trust.json, A = 255 on the tablet;
- ``uncertainty_um.npy``: σ_h in µm, float32, NaN off the tablet (what the viewer's ± of a
  distance or profile is computed from);
- ``trust.json``: the encodings, the class names, the legend scales in µm, the share of the
  tablet in each class and report.json's ``refinements`` (what each refinement did).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from worker.durable import npy_bytes
from worker.trust import (
    DISAGREE_K,
    RMS_SIGMA_PX,
    TRUST_CLASSES,
    encode_trust_rgba,
    height_uncertainty_um,
    legend_scale_um,
    normal_sigma_from_maps,
    trust_classes,
)

TRUST_ASSETS = ("trust.png", "trust.json", "uncertainty_um.npy")
QUALITY_INPUTS = (
    "fringe_disagreement_um",
    "guard",
    "walls",
    "photometric_residual",
    "lights_used",
)


def _load_quality(model_dir: Path, name: str, shape: tuple[int, int]) -> np.ndarray | None:
    """quality/<name>.npy if present and on the height's grid (else None: a map of another
    grid cannot be placed, and the trust map says less rather than something wrong)."""
    path = model_dir / "quality" / f"{name}.npy"
    if not path.is_file():
        return None
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return None
    return arr if arr.shape == shape else None


def trust_assets(model_dir: Path, height_um: np.ndarray, report: dict) -> dict[str, bytes]:
    """{name: bytes} of ``TRUST_ASSETS`` for a model directory (its quality maps read here)."""
    model_dir = Path(model_dir)
    q = {n: _load_quality(model_dir, n, height_um.shape) for n in QUALITY_INPUTS}
    normals = None
    if (model_dir / "normals.npy").is_file():
        try:
            normals = np.load(model_dir / "normals.npy", allow_pickle=False)
        except (OSError, ValueError):
            normals = None
    return trust_files(
        height_um,
        q,
        normals=normals,
        pixel_size_um=float(report["pixel_size_um"]),
        refinements=report.get("refinements", {}),
    )


def trust_maps(
    height_um: np.ndarray,
    quality: dict[str, np.ndarray | None],
    *,
    normals: np.ndarray | None,
    pixel_size_um: float,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """(classes, disagreement µm or None, σ_h µm) of one scan's grid from its quality maps
    (``QUALITY_INPUTS`` → array or None; a map not on the height's grid is ignored, so the
    trust map says less rather than something wrong)."""
    mask = np.isfinite(height_um)
    q = {
        n: (a if a is not None and np.shape(a) == height_um.shape else None)
        for n in QUALITY_INPUTS
        for a in [quality.get(n)]
    }
    d = q["fringe_disagreement_um"]
    sig_t = normal_sigma_from_maps(q["photometric_residual"], q["lights_used"])
    classes = trust_classes(mask, d, guard=q["guard"], walls=q["walls"])
    if normals is not None and np.shape(normals) != (*height_um.shape, 3):
        normals = None
    sigma = height_uncertainty_um(
        mask, d, pixel_size_um=pixel_size_um, normal_sigma=sig_t, guard=q["guard"], normals=normals
    )
    return classes, d, sigma


def trust_scales_um(
    classes: np.ndarray, disagreement_um: np.ndarray | None, sigma_um: np.ndarray
) -> tuple[float, float]:
    """The legend tops (µm) of one grid: (|fringe − final|, σ_h), ``legend_scale_um``."""
    mask = classes > 0
    d_scale = legend_scale_um(disagreement_um, mask) if disagreement_um is not None else 1.0
    return d_scale, legend_scale_um(sigma_um, mask)


def trust_files(
    height_um: np.ndarray,
    quality: dict[str, np.ndarray | None],
    *,
    normals: np.ndarray | None,
    pixel_size_um: float,
    refinements: dict | None = None,
    scales_um: tuple[float, float] | None = None,
    maps: tuple | None = None,
) -> dict[str, bytes]:
    """{name: bytes} of ``TRUST_ASSETS`` for one scan's grid. ``scales_um``: the legend tops
    (|fringe − final|, σ_h) to encode with, default this grid's own (a whole tablet passes one
    pair for all its faces, so one legend reads every face); ``maps``: `trust_maps`' result
    when already computed."""
    classes, d, sigma = maps or trust_maps(
        height_um, quality, normals=normals, pixel_size_um=pixel_size_um
    )
    mask = classes > 0
    d_scale, s_scale = scales_um or trust_scales_um(classes, d, sigma)
    rgba = encode_trust_rgba(
        classes, d, sigma, disagreement_scale_um=d_scale, sigma_scale_um=s_scale
    )
    ok, png = cv2.imencode(".png", np.ascontiguousarray(rgba[..., [2, 1, 0, 3]]))
    if not ok:
        raise OSError("trust.png: PNG encoding failed")
    n = max(int(mask.sum()), 1)
    meta = {
        "encoding": {
            "r": "source class (classes)",
            "g": "round(255·min(1, |fringe − final height| / disagreement_scale_um)), 0 without fringe height",
            "b": "round(255·min(1, σ_h / uncertainty_scale_um))",
            "a": "255 on the tablet",
        },
        "classes": {str(k): v for k, v in TRUST_CLASSES.items()},
        "class_fraction": {str(k): float((classes == k).sum() / n) for k in TRUST_CLASSES},
        # The grid's tablet pixels and pixel size: what a whole tablet weighs each face's
        # fractions by, and how a point (mm, scan frame) finds its pixel in uncertainty_um.npy.
        "pixels": int(mask.sum()),
        "pixel_size_um": float(pixel_size_um),
        "disagreement_scale_um": d_scale,
        "uncertainty_scale_um": s_scale,
        "median_uncertainty_um": float(np.nanmedian(sigma)) if mask.any() else None,
        "disagree_k": DISAGREE_K,
        "rms_sigma_px": RMS_SIGMA_PX,
        "inputs": sorted(n for n in QUALITY_INPUTS if np.shape(quality.get(n)) == height_um.shape),
        "refinements": refinements or {},
        "uncertainty_model": "worker/trust.py: local RMS of fringe − final height where "
        "fringes exist; elsewhere + pixel_size·σ_θ·√(distance in px to the nearest "
        "anchored pixel) in quadrature",
    }
    return {
        "trust.png": png.tobytes(),
        "trust.json": json.dumps(meta, indent=1, allow_nan=False).encode("utf-8"),
        "uncertainty_um.npy": npy_bytes(sigma),
    }
