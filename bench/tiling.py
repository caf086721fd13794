"""Tiling benchmark (issue 19): time, bytes, tile counts and peak memory of worker.tiles.

    .venv/bin/python bench/tiling.py [--work DIR] [--large 10000x10000] [--no-large]

1. A face at paper size (1280 × 1024 px of 26.8 µm): simulated (worker.simulate, `paper`
   preset, seed 0; kept in --work), reconstructed (`reconstruct_bundle`), its derived
   assets made, then tiled — each step in a fresh child process, timed, with the child's
   peak resident memory (getrusage ru_maxrss). Goal: tiling ≤ 2 × the reconstruction's own
   time for the face.
2. A 100 Mpx face (`worker.simulate.large_face`, no frames simulated; kept in --work):
   tiled in a child process. No reconstruction exists for it; the table shows the paper
   face's reconstruction time scaled by the pixel count for scale.

Prints a markdown table (docs/benchmarks.md keeps the last run).
"""

from __future__ import annotations

import sys
from pathlib import Path

# As bench/reconstruct.py: bench/queue.py must not shadow the standard library's queue.
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing as mp  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402


def _child(fn_name: str, args: tuple, queue) -> None:
    import importlib

    module, name = fn_name.rsplit(".", 1)
    fn = getattr(importlib.import_module(module), name)
    t0 = time.perf_counter()
    fn(*args)
    seconds = time.perf_counter() - t0
    queue.put((seconds, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0))


def timed(fn_name: str, *args) -> tuple[float, float]:
    """(seconds, peak RSS MiB) of fn(*args) in a fresh process."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(fn_name, args, queue))
    proc.start()
    result = queue.get()
    proc.join()
    if proc.exitcode != 0:
        raise RuntimeError(f"{fn_name} failed in its child process ({proc.exitcode})")
    return result


def _reconstruct(bundle: str, out: str) -> None:
    from worker.pipeline import reconstruct_bundle

    reconstruct_bundle(bundle, out)


def _simulate(out: str) -> None:
    from worker.simulate import simulate_scan

    simulate_scan(Path(out), seed=0, preset="paper", noise="default")


def _large(out: str, w: int, h: int) -> None:
    from worker.simulate.large_face import write_large_face

    write_large_face(out, width_px=w, height_px=h)


def _tile(model_dir: str) -> None:
    from worker.tiles import build_tiles

    build_tiles(model_dir)


def _copy_without_tiles(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("tiles", ".tiles*"))
    return dst


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "bench-tiling")
    parser.add_argument("--large", default="10000x10000", help="WxH of the large face")
    parser.add_argument("--no-large", action="store_true", help="only the paper-size face")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []

    # Everything heavy runs in child processes: a child's peak RSS (ru_maxrss) starts from
    # its parent's resident size at the fork, so this process stays small.
    scan = args.work / "paper-default-s0"
    if not (scan / "gt").exists():
        timed("__main__._simulate", str(scan))
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        model = Path(tmp) / "model"
        recon_s, recon_mib = timed("__main__._reconstruct", str(scan / "bundle"), str(model))
        assets_s, _ = timed("worker.assets.derive_assets", str(model))
        tile_s, tile_mib = timed("__main__._tile", str(model))
        index = json.loads((model / "tiles" / "index.json").read_text())
        paper_px = index["width_px"] * index["height_px"]
        rows.append(
            (
                f"paper face {index['width_px']} × {index['height_px']} (reconstructed)",
                recon_s,
                recon_mib,
                assets_s,
                tile_s,
                tile_mib,
                index,
            )
        )
    if not args.no_large:
        w, h = (int(v) for v in args.large.lower().split("x"))
        large = args.work / f"large-{w}x{h}"
        if not (large / "report.json").exists():
            seconds, mib = timed("__main__._large", str(large), w, h)
            print(f"(large face written in {seconds:.0f} s, peak {mib:.0f} MiB)", file=sys.stderr)
        with tempfile.TemporaryDirectory(dir=args.work) as tmp:
            model = _copy_without_tiles(large, Path(tmp) / "model")
            tile_s, tile_mib = timed("__main__._tile", str(model))
            index = json.loads((model / "tiles" / "index.json").read_text())
            scaled = rows[0][1] * (w * h) / paper_px
            rows.append(
                (f"large face {w} × {h} (procedural)", scaled, None, None, tile_s, tile_mib, index)
            )

    print(
        "| face | reconstruction s | recon peak MiB | assets s | tiling s | tiling / recon |"
        " tiling peak MiB | bytes (MiB) | 3D tiles | IIIF tiles | levels |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, recon_s, recon_mib, assets_s, tile_s, tile_mib, index in rows:
        st = index["stats"]
        recon = f"{recon_s:.2f}" if recon_mib is not None else f"({recon_s:.0f}, scaled)"
        print(
            f"| {name} | {recon} | {'—' if recon_mib is None else f'{recon_mib:.0f}'} | "
            f"{'—' if assets_s is None else f'{assets_s:.2f}'} | {tile_s:.2f} | "
            f"{tile_s / recon_s:.2f} | {tile_mib:.0f} | {st['bytes'] / 2**20:.1f} | "
            f"{st['tiles_3d']} | {st['tiles_iiif']} | {st['levels']} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
