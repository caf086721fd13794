"""The models bench/streaming.py measures, besides the 100 Mpx face (issue 19).

    .venv/bin/python bench/streaming_models.py --out DIR [--only face3|tablet13]

Writes DIR/face3 (a 2048 × 1536 procedural face, tiled) and DIR/tablet13/tablet (a whole
tablet of six procedural faces: obverse and reverse 2200 × 1700 px, the four edges 600 px
deep; 12.2 Mpx), from `worker.simulate.large_face` and tiled by the worker's own builders
(`worker.tiles.build.build_tiles`, `worker.tiles.tablet.build_tablet_tiles`). The faces are
placed as a box: the obverse as scanned (z = 0, seen along +z), the reverse 180° about y at
the tablet's thickness, each edge turned 90° so that it faces out of its side; from the
obverse view the four edges are edge-on, inside the frustum.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from worker.simulate.large_face import PIXEL_SIZE_UM, write_large_face
from worker.tiles.build import build_tiles
from worker.tiles.tablet import build_tablet_tiles

FACE_PX = (2200, 1700)
EDGE_PX = 600


def _rigid(rotation: np.ndarray, translation_mm) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation_mm
    return m


def tablet_transforms(width_mm: float, height_mm: float, depth_mm: float) -> dict[str, np.ndarray]:
    """Scan → tablet frame (mm) of each face of a box-shaped tablet. A scan frame has x right,
    y down and the camera looking along +z (heights toward it are z < 0); the tablet frame is
    the obverse's. Each edge's scan spans the box's side (x or y) by its depth."""
    w, h, d = width_mm, height_mm, depth_mm
    return {
        "obverse": np.eye(4),
        # 180° about y: x → w − x, z → d − z.
        "reverse": _rigid(np.diag([-1.0, 1.0, -1.0]), [w, 0.0, d]),
        # top (y = 0), seen from −y: scan x → x, scan y → −z (+ d), scan z → y.
        "top": _rigid(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), [0, 0, d]),
        # bottom (y = h), seen from +y: scan x → x, scan y → z, scan z → −y.
        "bottom": _rigid(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), [0, h, 0]),
        # left (x = 0), seen from −x: scan x → −z (+ d), scan y → y, scan z → x.
        "left": _rigid(np.array([[0, 0, 1.0], [0, 1, 0], [-1, 0, 0]]), [0, 0, d]),
        # right (x = w), seen from +x: scan x → z, scan y → y, scan z → −x.
        "right": _rigid(np.array([[0, 0, -1.0], [0, 1, 0], [1, 0, 0]]), [w, 0, 0]),
    }


def build_tablet13(out: Path) -> Path:
    w_px, h_px = FACE_PX
    mm = PIXEL_SIZE_UM / 1000
    sizes = {
        "obverse": (w_px, h_px),
        "reverse": (w_px, h_px),
        "top": (w_px, EDGE_PX),
        "bottom": (w_px, EDGE_PX),
        "left": (EDGE_PX, h_px),
        "right": (EDGE_PX, h_px),
    }
    moves = tablet_transforms(w_px * mm, h_px * mm, EDGE_PX * mm)
    faces = {}
    for k, (name, (fw, fh)) in enumerate(sizes.items()):
        d = out / name
        if not (d / "model.glb").is_file():
            write_large_face(d, width_px=fw, height_px=fh, seed=20 + k)
        faces[f"faces/{name}"] = (d, moves[name])
    tablet = out / "tablet"
    tablet.mkdir(parents=True, exist_ok=True)
    (tablet / "model.glb").write_bytes((out / "obverse" / "model.glb").read_bytes())
    (tablet / "report.json").write_text(json.dumps({"scans": list(sizes)}))
    build_tablet_tiles(tablet, faces)
    return tablet


def build_face3(out: Path) -> Path:
    write_large_face(out, width_px=2048, height_px=1536, seed=0)
    build_tiles(out)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--only", choices=["face3", "tablet13"])
    args = parser.parse_args()
    if args.only in (None, "face3"):
        print(build_face3(args.out / "face3"))
    if args.only in (None, "tablet13"):
        print(build_tablet13(args.out / "tablet13"))


if __name__ == "__main__":
    main()
