"""Reading model directories and writing the registration's output directory (atomically)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from worker.durable import replace_dir_atomic, write_new_file
from worker.register.pointcloud import ScanCloud, scan_cloud

__all__ = [
    "QUALITY_MAPS",
    "SHADING_MAPS",
    "RegisterInputError",
    "face_asset_dir",
    "load_model_dir",
    "png_bytes",
    "write_output_dir",
]

# A face model's image-grid shading maps (worker/assets.py) that the whole tablet serves per face.
SHADING_MAPS = ("curvature.png", "curvature_coarse.png", "accessibility.png")
# A face model's per-pixel quality maps (docs/reconstruction.md, quality/*.npy), carried into
# the whole tablet per face on the face's image grid (what a viewer shows as trust).
QUALITY_MAPS = (
    "photometric_residual.npy",
    "lights_used.npy",
    "fringe_modulation.npy",
    "fringe_disagreement_um.npy",
    "guard.npy",
)


def face_asset_dir(label: str) -> str:
    """Folder of a face's maps among the whole-tablet model's assets: ``faces/<label>`` with
    every character but letters, digits, '-', '_' and '.' replaced by '_' (the viewer's
    `faceAssetPrefix` applies the same rule to the GLB's node names)."""
    safe = "".join(ch if ch.isascii() and (ch.isalnum() or ch in "-_.") else "_" for ch in label)
    return f"faces/{safe.strip('.') or '_'}"


class RegisterInputError(ValueError):
    """A model directory cannot be used; the message names the directory and the file."""


def _image(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


def load_model_dir(path: str | os.PathLike) -> tuple[ScanCloud, dict]:
    """The model directory's scan as a ScanCloud plus its raw arrays (height, mask, albedo)."""
    d = Path(path)
    if not d.is_dir():
        raise RegisterInputError(f"{d}: not a model directory")
    try:
        report = json.loads((d / "report.json").read_text())
        height = np.load(d / "height.npy")
        normals = np.load(d / "normals.npy")
        mask = _image(d / "mask.png") > 127
        albedo = _image(d / "albedo.png") if (d / "albedo.png").exists() else None
    except FileNotFoundError as exc:
        raise RegisterInputError(f"{d}: missing {Path(exc.filename).name}") from None
    except (ValueError, OSError) as exc:
        raise RegisterInputError(f"{d}: unreadable ({exc})") from None
    scan = report.get("scan") or {}
    pixel = report.get("pixel_size_um")
    if not isinstance(pixel, (int, float)) or pixel <= 0:
        raise RegisterInputError(f"{d}/report.json: pixel_size_um missing or not > 0")
    face = scan.get("face") or "other"
    label = scan.get("id") or face
    pose = scan.get("pose")
    try:
        cloud = scan_cloud(
            height,
            normals,
            mask,
            albedo,
            pixel_size_um=float(pixel),
            label=str(label),
            face=str(face),
            pose=None if pose is None else np.asarray(pose, dtype=float),
        )
    except ValueError as exc:
        raise RegisterInputError(f"{d}: {exc}") from None
    return cloud, {
        "height_um": height,
        "normals": normals,
        "mask": mask,
        "albedo": albedo,
        "pixel_size_um": float(pixel),
        "tablet": scan.get("tablet") if isinstance(scan.get("tablet"), dict) else {},
        # The face model's shading maps, image grid, passed on as they are to the whole tablet.
        "shading_maps": {
            f.name: f.read_bytes() for f in sorted(d.glob("*.png")) if f.name in SHADING_MAPS
        },
        # Its quality maps likewise (bytes of the .npy files; the grid is the face's own).
        "quality_maps": {
            name: (d / "quality" / name).read_bytes()
            for name in QUALITY_MAPS
            if (d / "quality" / name).is_file()
        },
    }


def png_bytes(image: np.ndarray, *, px_per_mm: float, description: str) -> bytes:
    """PNG with its resolution in the pHYs chunk (dots per inch) and ``px_per_mm`` as text."""
    import io

    info = PngInfo()
    info.add_text("px_per_mm", f"{px_per_mm:.4f}")
    info.add_text("Description", description)
    buf = io.BytesIO()
    dpi = px_per_mm * 25.4
    Image.fromarray(np.asarray(image, np.uint8)).save(
        buf, format="PNG", pnginfo=info, dpi=(dpi, dpi)
    )
    return buf.getvalue()


def write_output_dir(out: str | os.PathLike, files: dict[str, bytes]) -> Path:
    """Write ``files`` (relative name → bytes) into ``out`` all at once: a temporary sibling
    directory, each file fsynced, then renamed; ``out`` must not exist or be empty."""
    target = Path(out)
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise FileExistsError(f"{target}: exists and is not an empty directory")

    def fill(tmp: Path) -> None:
        for name, data in files.items():
            write_new_file(tmp / name, data)

    replace_dir_atomic(target, fill)
    return target
