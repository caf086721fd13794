"""`python -m worker.reconstruct BUNDLE OUTDIR [--fusion default|paper|plain] [--surface ...]`.

Writes the model directory of SCAN_BUNDLE.md (plus quality/*.npy) with a progress bar on
stderr. Exit codes: 0 done, 2 the bundle cannot be reconstructed (message on stderr, OUTDIR
untouched).
"""

from __future__ import annotations

import argparse
import json
import sys

from worker.pipeline import FUSIONS, SURFACES, ReconstructionError, reconstruct_bundle


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m worker.reconstruct",
        description="Reconstruct a scan bundle (directory or .zip) into a model directory.",
    )
    parser.add_argument("bundle", help="scan bundle: a directory or a .zip")
    parser.add_argument("outdir", help="model directory to write (replaced atomically)")
    parser.add_argument("--fusion", choices=FUSIONS, default="default")
    parser.add_argument(
        "--surface",
        choices=SURFACES,
        default="fused",
        help="baseline surfaces for comparison: fringe heights alone, normals integrated alone",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    if args.quiet:  # not even imported (tqdm and its monitor thread cost ~0.1 s)
        bar = progress = None
    else:
        from tqdm import tqdm

        bar = tqdm(total=100, file=sys.stderr, unit="%", leave=False)

        def progress(stage: str, fraction: float) -> None:
            bar.set_description(stage)
            bar.update(max(0, round(100 * fraction) - bar.n))

    try:
        report = reconstruct_bundle(
            args.bundle, args.outdir, fusion=args.fusion, surface=args.surface, progress=progress
        )
    except ReconstructionError as exc:
        if bar is not None:
            bar.close()
        print(f"cannot reconstruct {args.bundle}: {exc}", file=sys.stderr)
        return 2
    if bar is not None:
        bar.close()
    for w in report["warnings"]:
        print(f"warning: {w}", file=sys.stderr)
    summary = {
        "outdir": args.outdir,
        "surface": report["surface"],
        "timings_s": report["timings_s"],
        "quality": report["quality"],
    }
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
