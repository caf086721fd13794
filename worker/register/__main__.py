"""CLI: ``python -m worker.register MODEL_DIR... OUTDIR [--dpi N] [--name NAME]``.

Writes OUTDIR/transforms.json, merged.ply, tablet.glb, report.json and the plates
fatcross/NAME_fatcross_{natural,curvature}.png, NAME_fatcross.pdf and one PNG per view.
Exit 0 on success, 2 on bad input (a clear message naming the culprit; nothing written).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from worker.register.io import RegisterInputError, write_output_dir
from worker.register.plates import DEFAULT_LICENCE
from worker.register.run import register_model_dirs


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m worker.register",
        description="Register a tablet's reconstructed scans, merge them, make fatcross plates.",
    )
    p.add_argument("paths", nargs="+", help="two or more model directories, then OUTDIR")
    p.add_argument("--dpi", type=float, default=600.0, help="fatcross resolution (default 600)")
    p.add_argument("--name", default="tablet", help="file name stem of the plates")
    p.add_argument("--designation", help="the plates' title (default: --name)")
    p.add_argument("--licence", default=DEFAULT_LICENCE, help="the plates' licence line")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if len(args.paths) < 3:
        print("error: give at least two model directories and an OUTDIR", file=sys.stderr)
        return 2
    *dirs, out = args.paths
    if not (10 <= args.dpi <= 4800):
        print(f"error: --dpi must be 10..4800, got {args.dpi}", file=sys.stderr)
        return 2
    if Path(out).exists() and (not Path(out).is_dir() or any(Path(out).iterdir())):
        print(f"error: OUTDIR {out} exists and is not empty", file=sys.stderr)
        return 2
    try:
        files, report = register_model_dirs(
            dirs,
            px_per_mm=args.dpi / 25.4,
            name=args.name,
            designation=args.designation,
            licence=args.licence,
        )
        write_output_dir(out, files)
    except (RegisterInputError, ValueError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for p in report["pairs"]:
        print(f"{p['a']} – {p['b']}: overlap {p['overlap']:.3f}, RMS {p['rms_um']:.1f} µm")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
