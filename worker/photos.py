"""The photographs a scan took, kept beside its model, and the gloss fitted from them.

    python -m worker.photos BUNDLE MODEL_DIR

Writes into MODEL_DIR (docs/viewer.md, "The photograph beside the render"):

- ``photos/index.json`` and one JPEG per light: every photometric frame of the object
  (grey) and every colour light (its red, green and blue frames as one RGB picture), as the
  camera saw them — linear radiance, one exposure scale for every picture so that their
  brightness compares, sRGB-encoded, at most ``PHOTO_MAX_PX`` on the long side (area
  resampling). The index gives each picture's light direction in the scan frame, so the
  viewer can show the photograph taken nearest to its own light.
- ``gloss.png`` and ``gloss.json``: the specular strength per pixel (red, scaled by
  ``strength_scale``; green 255 where fitted, 0 where filled from neighbours) and the
  scan's sharpness (``worker.recon.gloss``), or a report of why the fit stood down.

Reads the bundle through ``worker.bundle`` and the model's normals, mask and heights;
every file is written atomically (``worker.durable``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from worker.bundle import BundleError, open_bundle
from worker.durable import write_file_atomic
from worker.measure.photometric import decode_with_references, flat_fielded_shading
from worker.recon.color import linear_to_srgb8
from worker.recon.gloss import fit_gloss
from worker.recon.photometric import light_directions

__all__ = ["PHOTO_MAX_PX", "write_photo_assets"]

PHOTO_MAX_PX = 1024
JPEG_QUALITY = 88
EXPOSURE_PERCENTILE = 99.5


def _resize(image: np.ndarray, max_px: int) -> np.ndarray:
    h, w = image.shape[:2]
    scale = min(1.0, max_px / max(h, w))
    if scale >= 1.0:
        return image
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _jpeg(image_srgb8: np.ndarray) -> bytes:
    img = image_srgb8[..., ::-1] if image_srgb8.ndim == 3 else image_srgb8
    ok, buf = cv2.imencode(
        ".jpg", np.ascontiguousarray(img), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
    )
    if not ok:
        raise OSError("JPEG encoding failed")
    return buf.tobytes()


def _light(frame) -> list[float]:
    return [round(float(v), 6) for v in light_directions([frame.azimuth_deg], frame.polar_deg)[0]]


def _pictures(bundle, mask: np.ndarray) -> list[tuple[dict, np.ndarray]]:
    """(index entry, linear (H, W) or (H, W, 3) radiance) per light, object frames only."""
    obj = [f for f in bundle.frames if f.target == "object"]
    out: list[tuple[dict, np.ndarray]] = []
    for f in (f for f in obj if f.kind == "photometric"):
        entry = {"kind": "photometric", "frames": [f.index]}
        out.append((entry | _angles(f), bundle.radiance(f)))
    colour: dict[tuple[float, float], dict[str, object]] = {}
    for f in (f for f in obj if f.kind == "color"):
        colour.setdefault((float(f.polar_deg), float(f.azimuth_deg)), {})[f.channel] = f
    for (_, _), chans in sorted(colour.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        if set(chans) != {"red", "green", "blue"}:
            continue  # a light without its three channels is no colour picture
        frames = [chans[c] for c in ("red", "green", "blue")]
        rgb = np.stack([bundle.radiance(f) for f in frames], axis=-1)
        out.append(
            ({"kind": "color", "frames": [f.index for f in frames]} | _angles(frames[0]), rgb)
        )
    return out


def _angles(frame) -> dict:
    return {
        "azimuth_deg": float(frame.azimuth_deg),
        "polar_deg": float(frame.polar_deg),
        "light": _light(frame),
    }


def _photo_files(bundle, mask: np.ndarray) -> tuple[dict, dict[str, bytes]]:
    pictures = _pictures(bundle, mask)
    if not pictures:
        return {
            "version": 1,
            "photos": [],
            "note": "the bundle has no photometric or colour frames",
        }, {}
    # One exposure for all: the bright level of the object over every picture.
    inside = [p[mask] if p.ndim == 2 else p[mask].ravel() for _, p in pictures]
    bright = float(np.nanpercentile(np.concatenate(inside), EXPOSURE_PERCENTILE)) or 1.0
    files: dict[str, bytes] = {}
    entries = []
    for i, (entry, radiance) in enumerate(pictures):
        srgb = linear_to_srgb8(np.clip(radiance / np.float32(bright), 0, 1).astype(np.float32))
        small = _resize(srgb, PHOTO_MAX_PX)
        name = f"photos/{i:03d}-{entry['kind']}-az{entry['azimuth_deg']:05.1f}.jpg"
        files[name] = _jpeg(small)
        entries.append({"file": name} | entry)
    h, w = pictures[0][1].shape[:2]
    ph, pw = _resize(np.zeros((h, w), np.uint8), PHOTO_MAX_PX).shape
    index = {
        "version": 1,
        "frame": "scan (SCAN_BUNDLE.md): light = direction toward the source",
        "source_size_px": [w, h],
        "size_px": [pw, ph],
        "exposure": f"linear radiance / its {EXPOSURE_PERCENTILE}th percentile on the object, sRGB",
        "photos": entries,
    }
    return index, files


def _shading_noise(shading: np.ndarray, mask: np.ndarray) -> float:
    """σ of one shading sample from neighbour differences (MAD; texture only inflates it,
    which makes the gloss fit more reluctant, never bolder)."""
    s = np.nanmedian(shading, axis=0)
    d = (s[:, 1:] - s[:, :-1])[mask[:, 1:] & mask[:, :-1]]
    d = d[np.isfinite(d)]
    if d.size < 100:
        return float("inf")
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2))


def _gloss_files(bundle, model_dir: Path, mask: np.ndarray) -> dict[str, bytes]:
    photo = [f for f in bundle.frames if f.target == "object" and f.kind == "photometric"]
    normals = np.load(model_dir / "normals.npy")
    height = np.load(model_dir / "height.npy")
    report: dict = {"version": 1, "model": "Blinn-Phong lobe k_s·max(0, n·h)^alpha (Blinn 1977)"}
    if len(photo) < 3:
        report["stood_down"] = "fewer than 3 photometric frames"
        return {"gloss.json": json.dumps(report, indent=2).encode()}
    pixel_size_um = float(bundle.manifest.camera.pixel_size_um)
    stack, ref_stack = decode_with_references(bundle, photo)
    rough = np.where(np.isfinite(height), height, np.nanmedian(height)).astype(np.float32)
    shading, warnings = flat_fielded_shading(
        bundle,
        photo,
        stack,
        float(bundle.manifest.reference.reflectance),
        ref_stack=ref_stack,
        height_um=rough,
        pixel_size_um=pixel_size_um,
    )
    del stack, ref_stack
    lights = light_directions([f.azimuth_deg for f in photo], [f.polar_deg for f in photo])
    sigma = _shading_noise(shading, mask)
    res = fit_gloss(shading, lights, normals, mask, noise_sigma=sigma)
    report |= res.report | {"noise_sigma": sigma, "warnings": warnings}
    if res.exponent is None:
        return {"gloss.json": json.dumps(report, indent=2).encode()}
    scale = float(max(np.percentile(res.strength[mask], 99.9), 1e-6))
    rgb = np.zeros((*mask.shape, 3), np.uint8)
    rgb[..., 0] = np.clip(np.rint(res.strength / scale * 255), 0, 255).astype(np.uint8)
    rgb[..., 1] = np.where(res.identified, 255, 0).astype(np.uint8)
    ok, buf = cv2.imencode(".png", rgb[..., ::-1])
    if not ok:
        raise OSError("gloss.png: PNG encoding failed")
    report |= {
        "exponent": res.exponent,
        "strength_scale": scale,
        "encoding": "gloss.png: red = round(255·k_s/strength_scale); green = 255 fitted, 0 filled",
    }
    return {"gloss.json": json.dumps(report, indent=2).encode(), "gloss.png": buf.tobytes()}


def write_photo_assets(bundle_path: str | Path, model_dir: str | Path) -> list[str]:
    """Write the photo stack and the gloss of ``bundle_path`` into ``model_dir``; the names
    written (relative to ``model_dir``)."""
    model_dir = Path(model_dir)
    mask = cv2.imread(str(model_dir / "mask.png"), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise ValueError(f"{model_dir}: no mask.png (not a model directory)")
    mask = mask == 255
    with open_bundle(bundle_path) as bundle:
        index, files = _photo_files(bundle, mask)
        files |= _gloss_files(bundle, model_dir, mask)
    for name, data in files.items():
        (model_dir / name).parent.mkdir(parents=True, exist_ok=True)
        write_file_atomic(model_dir / name, data)
    # The index last: its presence means the pictures it lists are all there.
    (model_dir / "photos").mkdir(exist_ok=True)
    write_file_atomic(model_dir / "photos" / "index.json", json.dumps(index, indent=2).encode())
    return [*files, "photos/index.json"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m worker.photos", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("bundle", type=Path)
    p.add_argument("model_dir", type=Path)
    args = p.parse_args(argv)
    try:
        names = write_photo_assets(args.bundle, args.model_dir)
    except (BundleError, ValueError, OSError) as exc:
        print(f"worker.photos: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(names)} files into {args.model_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
