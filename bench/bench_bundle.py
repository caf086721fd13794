"""Speed of worker.bundle on a camera-sized bundle: write, open, validate, radiance.

    .venv/bin/python bench/bench_bundle.py [--frames 400] [--width 1280] [--height 1024]

Images are 12-bit in 16-bit PNGs: a smooth shading plus Gaussian noise (σ = 8 DN), so the
PNGs compress like real camera frames. Prints a table of seconds and ms per frame.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from worker.bundle import open_bundle, validate_bundle, write_bundle
from worker.bundle.images import decode_png_cv2, decode_png_pillow, decode_tiff
from worker.bundle.writer import encode_image


def make_bundle(n_frames: int, width: int, height: int) -> tuple[dict, dict[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:height, 0:width]
    frames = [{"file": "dark.png", "kind": "dark"}]
    images = {"dark.png": rng.normal(60, 4, (height, width)).clip(0, 4095).astype(np.uint16)}
    for i in range(n_frames - 1):
        azimuth = 360.0 * i / (n_frames - 1)
        shade = 1500 + 1000 * np.cos(np.radians(azimuth) + xx / width + yy / height)
        frames.append({"file": f"img/p{i:04d}.png", "kind": "photometric", "azimuth_deg": azimuth})
        noisy = shade + rng.normal(0, 8, (height, width))
        images[frames[-1]["file"]] = noisy.clip(0, 4095).astype(np.uint16)
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {"face": "obverse"},
        "camera": {"width": width, "height": height, "pixel_size_um": 20, "bit_depth": 12},
        "source": {"polar_deg": 45},
        "frames": frames,
    }
    return manifest, images


def timed(fn):
    start = time.perf_counter()
    result = fn()
    return time.perf_counter() - start, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=1024)
    args = parser.parse_args()
    n = args.frames
    manifest, images = make_bundle(n, args.width, args.height)
    rows = []
    work = Path(tempfile.mkdtemp(prefix="bench_bundle_"))
    try:
        for as_zip in (False, True):
            label = "zip" if as_zip else "dir"
            out = work / ("b.zip" if as_zip else "b")
            t, _ = timed(
                lambda out=out, as_zip=as_zip: write_bundle(out, manifest, images, as_zip=as_zip)
            )
            rows.append((f"{label}: write_bundle", t, n))
            t, bundle = timed(lambda out=out: open_bundle(out))
            rows.append((f"{label}: open_bundle (headers)", t, n))
            with bundle:
                lit = bundle.frames[1:]
                t, _ = timed(lambda b=bundle, lit=lit: [b.radiance(f) for f in lit])
                rows.append((f"{label}: radiance, one by one", t, len(lit)))
                for workers in (1, 2):
                    t, _ = timed(
                        lambda b=bundle, lit=lit, w=workers: b.radiance_many(lit, max_workers=w)
                    )
                    rows.append((f"{label}: radiance_many, {workers} thread(s)", t, len(lit)))
            t, problems = timed(lambda out=out: validate_bundle(out))
            assert problems == [], problems
            rows.append((f"{label}: validate_bundle (decodes all)", t, n))
        data = (work / "b" / manifest["frames"][1]["file"]).read_bytes()
        tiff = encode_image("x.tif", images[manifest["frames"][1]["file"]])
        for name, decoder, blob in (
            ("PNG, cv2.imdecode", decode_png_cv2, data),
            ("PNG, Pillow", decode_png_pillow, data),
            ("uncompressed TIFF, tifffile", decode_tiff, tiff),
        ):
            t, _ = timed(lambda d=decoder, b=blob: [d(b) for _ in range(20)])
            rows.append((f"decode one 16-bit {name} ({len(blob) / 1e6:.1f} MB)", t, 20))
        size_mb = sum(p.stat().st_size for p in (work / "b").rglob("*") if p.is_file()) / 1e6
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(
        f"{n} frames of {args.width}×{args.height} 12-bit in 16-bit PNG, {size_mb:.0f} MB on disk"
    )
    print(f"{'step':52s} {'total s':>9s} {'ms/frame':>9s}")
    for name, seconds, count in rows:
        print(f"{name:52s} {seconds:9.2f} {1000 * seconds / count:9.1f}")


if __name__ == "__main__":
    main()
