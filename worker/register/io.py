"""Reading model directories and writing the registration's output directory (atomically)."""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path

import numpy as np
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from worker.durable import replace_dir_atomic, write_new_file
from worker.register.pointcloud import ScanCloud, scan_cloud

log = logging.getLogger("worker.register.io")

__all__ = [
    "GLOSS_FILES",
    "QUALITY_MAPS",
    "SHADING_MAPS",
    "RegisterInputError",
    "face_asset_dir",
    "load_model_dir",
    "photo_asset_names",
    "png_bytes",
    "write_output_dir",
]

# A face model's image-grid shading maps (worker/assets.py) that the whole tablet serves per face.
SHADING_MAPS = ("curvature.png", "curvature_coarse.png", "accessibility.png")
# A face model's measured gloss (worker/photos.py), carried into the whole tablet per face.
GLOSS_FILES = ("gloss.png", "gloss.json")
# A photograph's name in photos/index.json (worker/photos.py writes photos/NNN-kind-azA.jpg);
# anything else (a path out of photos/, another type) is never copied.
_PHOTO_NAME = re.compile(r"^photos/[A-Za-z0-9][A-Za-z0-9._-]*\.jpe?g$")

# A face model's per-pixel quality maps (docs/reconstruction.md, quality/*.npy), carried into
# the whole tablet per face on the face's image grid (what a viewer shows as trust).
QUALITY_MAPS = (
    "photometric_residual.npy",
    "lights_used.npy",
    "fringe_modulation.npy",
    "fringe_disagreement_um.npy",
    "guard.npy",
    "walls.npy",  # where a refinement changed the heights (the trust map's "refined" class)
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
        # What each refinement did (report.json), for the face's trust.json.
        "refinements": report.get("refinements")
        if isinstance(report.get("refinements"), dict)
        else {},
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
        # Its photographs and measured gloss (worker/photos.py), passed on as they are.
        "photo_files": face_photo_files(d),
    }


def photo_asset_names(index_bytes: bytes) -> list[str]:
    """The photographs a face model's ``photos/index.json`` lists (their names relative to
    the model), in its order; ValueError naming the entry when one is not a JPEG under
    ``photos/`` (never a path out of it) or the index is not worker/photos.py's."""
    index = json.loads(index_bytes)
    photos = index.get("photos") if isinstance(index, dict) else None
    if not isinstance(photos, list):
        raise ValueError("photos/index.json: no 'photos' list")
    names = []
    for i, entry in enumerate(photos):
        name = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(name, str) or not _PHOTO_NAME.match(name) or ".." in name:
            raise ValueError(
                f"photos/index.json: photos[{i}].file {name!r} is not photos/<name>.jpg"
            )
        names.append(name)
    return names


def face_photo_files(d: Path) -> dict[str, bytes]:
    """A face model's photographs (``photos/index.json`` and the JPEGs it lists) and gloss
    (``gloss.png``, ``gloss.json``), name → bytes; the photographs are left out, with a
    warning, when the index or one of its pictures is unusable (they are an extra: the whole
    tablet is still made), never copied in part."""
    out = {name: (d / name).read_bytes() for name in GLOSS_FILES if (d / name).is_file()}
    index = d / "photos" / "index.json"
    if not index.is_file():
        return out
    try:
        data = index.read_bytes()
        photos = {name: (d / name).read_bytes() for name in photo_asset_names(data)}
    except (ValueError, OSError) as exc:
        log.warning("%s: photographs left out: %s", d, exc)
        return out
    return out | photos | {"photos/index.json": data}


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
