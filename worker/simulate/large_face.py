"""A large procedurally generated tablet face written straight to a model directory.

For the scale tests of issue 19 (a 100 Mpx face, e.g. 10,000 × 10,000 px at 26.8 µm, as a
tablet scanned in tiles on x/y stages): no frames are simulated; the model directory of
SCAN_BUNDLE.md ("Reconstruction output") is written from the ground-truth surface itself,
with the derived maps of `worker.assets` (curvature; accessibility on heights averaged to
at most 4 Mpx, as its 3 mm horizon varies slowly).

The surface: a cushion-shaped tablet (a superellipse outline, a dome of 1.5 % of its width)
with lines of cuneiform wedges, each a triangular-pyramid head (three planar facets, the
stylus corner) and a V-groove tail (`worker.simulate.carvings` models the same two parts
as polyhedra; here they are height functions, cheap at 10^4 wedges). Normals by central
differences of the heights (`worker.recon.plain.normals_from_height`), albedo a clay colour
with a little low-frequency variation, darker in the wedges.

Memory: everything is made by blocks of rows (float32, a halo where a filter needs one);
the full-size arrays kept at once are the float32 height (4 B/px) and the uint8 images.

CLI: ``python -m worker.simulate.large_face --out DIR --width 10000 --height 10000``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import cv2
import numpy as np

from worker.durable import replace_dir_atomic, write_new_file
from worker.recon.glb import glb_bytes
from worker.recon.plain import normals_from_height
from worker.recon.shading_maps import (
    accessibility,
    encode_signed8,
    encode_unit8,
    mean_curvature_per_um,
    normals_rgb8,
    robust_scale,
)

__all__ = ["large_face_height_um", "main", "write_large_face"]

PIXEL_SIZE_UM = 26.8
BLOCK_ROWS = 512
WEDGE_DEPTH_UM = 250.0
WEDGE_SLOPE = 0.5  # facet rise per unit run (≈ 27°)
CURVATURE_SCALE_UM = 200.0
ACCESSIBILITY_RADIUS_UM = 3000.0


def _wedges(width_px: int, height_px: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 5) wedges: apex column, apex row (px), direction (rad), head size, tail length (px)."""
    line_px = max(20.0, 4000.0 / PIXEL_SIZE_UM)  # a line of script every 4 mm
    head_px = 0.3 * line_px
    out = []
    for row in np.arange(1.0 * line_px, height_px - 0.7 * line_px, line_px):
        col = 0.8 * line_px + rng.uniform(0, 0.5) * line_px
        while col < width_px - 0.8 * line_px:
            direction = rng.choice([0.0, np.pi / 2, np.pi / 4, -np.pi / 4])
            size = head_px * rng.uniform(0.7, 1.2)
            tail = size * rng.uniform(0.0, 2.5) if direction == 0.0 else size * rng.uniform(0, 1)
            out.append((col, row + rng.uniform(-0.1, 0.1) * line_px, direction, size, tail))
            col += size * rng.uniform(1.6, 3.0) + (tail if direction == 0.0 else 0.0)
    return np.asarray(out, np.float64).reshape(-1, 5)


def _outline(width_px: int, height_px: int, rows: np.ndarray, cols: np.ndarray):
    """Normalised coordinates (−1 … 1) and the superellipse ρ (< 1 inside) on a block."""
    u = (cols[None, :] + 0.5) / width_px * 2 - 1
    v = (rows[:, None] + 0.5) / height_px * 2 - 1
    rho = (np.abs(u / 0.96) ** 6 + np.abs(v / 0.96) ** 6) ** (1 / 6)
    return u, v, rho


def _block_height(width_px, height_px, r0, r1, wedges) -> np.ndarray:
    rows = np.arange(r0, r1, dtype=np.float64)
    cols = np.arange(width_px, dtype=np.float64)
    u, v, rho = _outline(width_px, height_px, rows, cols)
    dome_um = 0.015 * width_px * PIXEL_SIZE_UM
    h = (dome_um * (1 - np.clip(u * u + v * v, 0, 2) / 2)).astype(np.float32)
    h = np.broadcast_to(h, (len(rows), width_px)).copy()
    reach = wedges[:, 3] + wedges[:, 4] + 2
    near = (wedges[:, 1] + reach > r0) & (wedges[:, 1] - reach < r1)
    s_um = PIXEL_SIZE_UM
    for cx, cy, ang, size, tail in wedges[near]:
        ext = size + tail + 2
        c0, c1 = int(max(0, cx - ext)), int(min(width_px, cx + ext + 1))
        q0, q1 = int(max(r0, cy - ext)), int(min(r1, cy + ext + 1))
        if c0 >= c1 or q0 >= q1:
            continue
        yy, xx = np.mgrid[q0:q1, c0:c1].astype(np.float64)
        dx, dy = xx - cx, yy - cy
        d = np.array([np.cos(ang), np.sin(ang)])
        # Head: three facets rising from the apex, one facing each corner of the triangle.
        head = np.full(dx.shape, -np.inf)
        for k in range(3):
            a = ang + np.pi + 2 * np.pi * k / 3
            head = np.maximum(head, dx * np.cos(a) + dy * np.sin(a))
        depth = -WEDGE_DEPTH_UM * size / 30.0 + WEDGE_SLOPE * s_um * head * 2.0
        # Tail: a V-groove along d rising to the surface after `tail` px.
        t = dx * d[0] + dy * d[1]
        perp = np.abs(-dx * d[1] + dy * d[0])
        tail_depth = np.where(
            (t >= 0) & (t <= tail),
            -WEDGE_DEPTH_UM * size / 30.0 * (1 - t / max(tail, 1e-9)) * 0.6
            + WEDGE_SLOPE * s_um * perp * 2.0,
            np.inf,
        )
        cut = np.minimum(np.minimum(depth, tail_depth), 0.0).astype(np.float32)
        h[q0 - r0 : q1 - r0, c0:c1] += cut
    return np.where(rho < 1.0, h, np.nan).astype(np.float32)


def large_face_height_um(width_px: int, height_px: int, *, seed: int = 0) -> np.ndarray:
    """(H, W) float32 heights in µm (NaN outside the tablet), made by blocks of rows."""
    wedges = _wedges(width_px, height_px, np.random.default_rng(seed))
    out = np.empty((height_px, width_px), np.float32)
    for r0 in range(0, height_px, BLOCK_ROWS):
        r1 = min(height_px, r0 + BLOCK_ROWS)
        out[r0:r1] = _block_height(width_px, height_px, r0, r1, wedges)
    return out


def _by_blocks(height_um: np.ndarray, halo: int, fn, out: np.ndarray) -> None:
    """out[rows] = fn(height of rows ± halo)[the rows], block by block."""
    h = height_um.shape[0]
    for r0 in range(0, h, BLOCK_ROWS):
        r1 = min(h, r0 + BLOCK_ROWS)
        a0, a1 = max(0, r0 - halo), min(h, r1 + halo)
        out[r0:r1] = fn(height_um[a0:a1])[r0 - a0 : r0 - a0 + (r1 - r0)]


def _accessibility(h: np.ndarray) -> np.ndarray:
    """Accessibility (worker.recon.shading_maps) over a 3 mm radius, computed on heights
    averaged over `factor` × `factor` pixels (at most ~4 Mpx) and resized back: the horizon
    over 3 mm (112 px) varies slowly, and the full-resolution computation of a 100 Mpx face
    would take an hour of CPU."""
    rows, cols = h.shape
    factor = 1
    while (rows // factor) * (cols // factor) > 4_000_000:
        factor *= 2
    if factor == 1:
        small = h
    else:
        r, c = rows // factor * factor, cols // factor * factor
        shape = (r // factor, factor, c // factor, factor)
        finite = np.isfinite(h[:r, :c])
        total = np.where(finite, h[:r, :c], 0.0).reshape(shape).sum(axis=(1, 3))
        count = finite.reshape(shape).sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            small = np.where(count > 0, total / count, np.nan).astype(np.float32)
    acc = accessibility(
        small, pixel_size_um=PIXEL_SIZE_UM * factor, radius_um=ACCESSIBILITY_RADIUS_UM
    )
    if factor > 1:
        acc = cv2.resize(np.nan_to_num(acc, nan=1.0), (cols, rows), interpolation=cv2.INTER_LINEAR)
    return np.where(np.isfinite(h), acc, np.nan).astype(np.float32)


def _png(image: np.ndarray, name: str) -> bytes:
    img = image[..., ::-1] if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise OSError(f"{name}: PNG encoding failed")
    return buf.tobytes()


def write_large_face(out_dir: str | Path, *, width_px: int, height_px: int, seed: int = 0) -> dict:
    """Write the model directory; returns its report."""
    if width_px < 16 or height_px < 16:
        raise ValueError(f"the face must be at least 16 × 16 px, got {width_px} × {height_px}")
    h = large_face_height_um(width_px, height_px, seed=seed)
    mask = np.isfinite(h)
    normals = np.empty((height_px, width_px, 3), np.float32)
    _by_blocks(h, 1, lambda b: normals_from_height(b, pixel_size_um=PIXEL_SIZE_UM), normals)
    # Albedo: clay, a few long waves of ±6 %, darker (−25 %) at the bottom of the wedges.
    albedo = np.empty((height_px, width_px, 3), np.uint8)
    clay = np.array([178.0, 148.0, 112.0], np.float32)
    cols = np.arange(width_px, dtype=np.float32)
    for r0 in range(0, height_px, BLOCK_ROWS):
        r1 = min(height_px, r0 + BLOCK_ROWS)
        rr = np.arange(r0, r1, dtype=np.float32)[:, None]
        wave = 0.04 * np.sin(cols / 700.0 + rr / 1100.0) + 0.02 * np.sin(
            cols / 230.0 - rr / 310.0 + 1.0
        )
        n_z = np.nan_to_num(-normals[r0:r1, :, 2], nan=1.0)
        shade = 1.0 + wave - 0.25 * np.clip((1 - n_z) * 4, 0, 1)
        albedo[r0:r1] = np.clip(clay * shade[..., None], 0, 255).astype(np.uint8)
    curv = np.empty(h.shape, np.float32)
    sigma_px = CURVATURE_SCALE_UM / PIXEL_SIZE_UM
    _by_blocks(
        h,
        int(4 * sigma_px) + 2,
        lambda b: mean_curvature_per_um(
            b, pixel_size_um=PIXEL_SIZE_UM, scale_um=CURVATURE_SCALE_UM
        ),
        curv,
    )
    acc = _accessibility(h)
    curv_scale = robust_scale(curv[:: max(1, height_px // 1000), :: max(1, width_px // 1000)])
    report = {
        "simulated": True,
        "generator": "worker.simulate.large_face",
        "seed": seed,
        "pixel_size_um": PIXEL_SIZE_UM,
        "image_size": {"width": width_px, "height": height_px},
        "note": "procedural surface written as a model directory; no frames were simulated",
    }
    albedo_png = _png(albedo, "albedo.png")
    normals_png = _png(normals_rgb8(normals), "normals.png")

    def fill(tmp: Path) -> None:
        # np.save straight to the files: a bytes copy of the normals would be 1.2 GB more.
        for name, arr in (("height.npy", h), ("normals.npy", normals)):
            with open(tmp / name, "xb") as fh:
                np.save(fh, arr, allow_pickle=False)
                fh.flush()
                os.fsync(fh.fileno())
        write_new_file(tmp / "albedo.png", albedo_png)
        write_new_file(tmp / "normals.png", normals_png)
        write_new_file(tmp / "mask.png", _png(np.where(mask, 255, 0).astype(np.uint8), "mask"))
        write_new_file(tmp / "curvature.png", _png(encode_signed8(curv, scale=curv_scale), "c"))
        write_new_file(tmp / "accessibility.png", _png(encode_unit8(acc), "accessibility.png"))
        shading = {
            "curvature": {
                "curvature.png": {
                    "smoothing_sigma_um": CURVATURE_SCALE_UM,
                    "encoding": "grey = 128 + 127.5·tanh(H / scale_per_um), H in 1/µm",
                    "scale_per_um": curv_scale,
                }
            },
            "accessibility": {
                "radius_um": ACCESSIBILITY_RADIUS_UM,
                "encoding": "grey = 255·accessibility",
            },
        }
        write_new_file(tmp / "shading.json", json.dumps(shading, indent=1).encode())
        glb, info = glb_bytes(
            h, mask, normals, albedo, pixel_size_um=PIXEL_SIZE_UM, albedo_png=albedo_png
        )
        write_new_file(tmp / "model.glb", glb)
        report["mesh"] = {"glb_vertices": info["vertices"], "glb_triangles": info["triangles"]}
        write_new_file(tmp / "report.json", json.dumps(report, indent=1).encode())

    replace_dir_atomic(out_dir, fill)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m worker.simulate.large_face", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--out", required=True, type=Path, help="model directory to write")
    parser.add_argument("--width", type=int, default=10_000, help="pixels (default 10000)")
    parser.add_argument("--height", type=int, default=10_000, help="pixels (default 10000)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        report = write_large_face(
            args.out, width_px=args.width, height_px=args.height, seed=args.seed
        )
    except ValueError as exc:
        print(f"large_face: {exc}", file=sys.stderr)
        return 2
    size = report["image_size"]
    print(f"{args.out}: {size['width']} × {size['height']} px at {PIXEL_SIZE_UM} µm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
