"""IIIF Image API 3.0 level-0 static tiles of one image layer, written by libvips' dzsave.

`dzsave(layout="iiif3")` writes `<dir>/info.json` and the tiles as
`<region>/<size>/0/default.<ext>` for every scale factor (IIIF Image API 3.0 §4, §5.6);
the `id` in info.json is a placeholder that the API replaces with the public URL of the
layer at serve time (docs/tiles.md). We add the `sizes` of the whole-image renditions
dzsave wrote (`full/<w>,<h>/…`), which level-0 clients use for thumbnails (§5.3).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyvips

__all__ = ["PLACEHOLDER_ID", "TILE_PX", "save_layer"]

# The id prefix written on disk; backend/api/models.py swaps it for the public base URL.
PLACEHOLDER_ID = "https://hammurabi.invalid/iiif-placeholder"
TILE_PX = 512

_FORMATS = {np.dtype(np.uint8): "uchar", np.dtype(np.uint16): "ushort"}


def _vips_image(image: np.ndarray | Path) -> pyvips.Image:
    if isinstance(image, Path):
        return pyvips.Image.new_from_file(str(image), access="sequential")
    arr = np.ascontiguousarray(image)
    bands = 1 if arr.ndim == 2 else arr.shape[2]
    img = pyvips.Image.new_from_memory(
        arr.data, arr.shape[1], arr.shape[0], bands, _FORMATS[arr.dtype]
    )
    if arr.dtype == np.uint16:
        img = img.copy(interpretation="grey16")
    return img


def save_layer(image: np.ndarray | Path, out_dir: Path, *, suffix: str) -> int:
    """Write the layer's tiles into `out_dir` (which must not exist); returns the number of
    tile files. `image`: an array (H, W[, C]) uint8/uint16 or an image file; `suffix`:
    libvips' save options, e.g. ".jpg[Q=90]" or ".png"."""
    img = _vips_image(image)
    name = out_dir.name
    img.dzsave(
        str(out_dir),
        layout="iiif3",
        tile_size=TILE_PX,
        overlap=0,
        suffix=suffix,
        id=PLACEHOLDER_ID,
        keep="none",
    )
    (out_dir.parent / "vips-properties.xml").unlink(missing_ok=True)
    (out_dir / "vips-properties.xml").unlink(missing_ok=True)
    info_path = out_dir / "info.json"
    info = json.loads(info_path.read_text(encoding="utf-8"))
    info["id"] = f"{PLACEHOLDER_ID}/{name}"
    sizes = []
    full = out_dir / "full"
    if full.is_dir():
        for d in full.iterdir():
            w, h = (int(v) for v in d.name.split(","))
            sizes.append({"width": w, "height": h})
    info["sizes"] = sorted(sizes, key=lambda s: s["width"])
    info_path.write_text(json.dumps(info, indent=1), encoding="utf-8")
    return sum(1 for p in out_dir.rglob("*") if p.is_file() and p.name != "info.json")
