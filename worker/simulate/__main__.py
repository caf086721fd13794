"""CLI: ``python -m worker.simulate --out DIR [--seed N] [--size WxH] [--tablet-mm WxHxT]
[--pixel-um S] [--face F] [--preset P]
[--noise N] [--physics NAME|random] [--physics-seed N] [--zip]
[--renderer native|mitsuba [--spp N] [--max-depth N]]``. Exit 0 on success, 2 on bad
arguments (clear message, nothing written)."""

from __future__ import annotations

import argparse
import sys

from worker.simulate.acquisition import PRESETS
from worker.simulate.noise import NOISE_PRESETS
from worker.simulate.physics import PHYSICS_VARIANTS
from worker.simulate.scan import parse_size, simulate_scan
from worker.simulate.tablet import FACES, check_size_mm


def _size(text: str) -> tuple[int, int]:
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _tablet_mm(text: str) -> tuple[float, float, float]:
    try:
        w, h, t = (float(v) for v in text.lower().split("x"))
        check_size_mm((w, h, t))
    except ValueError as exc:
        detail = str(exc) if "tablet size" in str(exc) else f"expected WxHxT in mm, got {text!r}"
        raise argparse.ArgumentTypeError(detail) from None
    return w, h, t


def _pixel_um(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of µm, got {text!r}") from None
    if not 1.0 <= value <= 2000.0:
        raise argparse.ArgumentTypeError(f"must be 1..2000 µm, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m worker.simulate",
        description="Simulate a scan bundle of a synthetic cuneiform tablet, with ground truth.",
    )
    p.add_argument("--out", required=True, help="output folder (bundle/ and gt/ are made in it)")
    p.add_argument("--seed", type=int, default=0, help="tablet, instrument and noise seed")
    p.add_argument("--size", type=_size, default=None, help="WIDTHxHEIGHT (default: the preset's)")
    p.add_argument(
        "--tablet-mm",
        type=_tablet_mm,
        default=None,
        metavar="WxHxT",
        help="the synthetic tablet's width, height and thickness in mm (default 28x22x12); "
        "without --size each face's frame then follows the tablet at --pixel-um",
    )
    p.add_argument(
        "--pixel-um",
        type=_pixel_um,
        default=None,
        help="pixel size on the object in µm (with --tablet-mm default 26.8, the paper's); "
        "without --size the frame follows the tablet",
    )
    p.add_argument("--face", choices=[*FACES, "all"], default="obverse")
    p.add_argument("--preset", choices=sorted(PRESETS), default="quick")
    p.add_argument("--noise", choices=sorted(NOISE_PRESETS), default="default")
    p.add_argument(
        "--mesh",
        default=None,
        help="scan this triangle mesh (PLY/OBJ/STL, mm, obverse toward -z) instead",
    )
    p.add_argument(
        "--physics",
        choices=[*PHYSICS_VARIANTS, "random"],
        default="ideal",
        metavar="NAME|random",
        help="instrument physics: a named variant ("
        + ", ".join(PHYSICS_VARIANTS)
        + ") or 'random' (drawn from --physics-seed); recorded in gt/physics.json",
    )
    p.add_argument(
        "--physics-seed",
        type=int,
        default=None,
        help="seed of the random physics draw (default: --seed)",
    )
    p.add_argument("--zip", action="store_true", help="write bundle.zip instead of bundle/")
    p.add_argument(
        "--renderer",
        choices=("native", "mitsuba"),
        default="native",
        help="light transport: our forward model, or Mitsuba 3's path tracer (docs/simulator.md)",
    )
    p.add_argument("--spp", type=int, default=None, help="mitsuba: samples per pixel (16)")
    p.add_argument(
        "--max-depth", type=int, default=None, help="mitsuba: path length (3: one bounce)"
    )
    return p


def _render_mitsuba(args: argparse.Namespace):
    from worker.simulate.mitsuba import MitsubaUnavailable, render_scan_mitsuba

    try:
        return render_scan_mitsuba(
            args.out,
            seed=args.seed,
            size=args.size,
            face=args.face,
            preset=args.preset,
            noise=args.noise,
            mesh=args.mesh,
            physics=args.physics,
            physics_seed=args.physics_seed,
            spp=16 if args.spp is None else args.spp,
            max_depth=3 if args.max_depth is None else args.max_depth,
            as_zip=args.zip,
            progress=True,
        )
    except MitsubaUnavailable as exc:
        raise ValueError(str(exc)) from None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.seed < 0:
        build_parser().error(f"argument --seed: must be >= 0, got {args.seed}")
    if args.physics_seed is not None and args.physics_seed < 0:
        build_parser().error(f"argument --physics-seed: must be >= 0, got {args.physics_seed}")
    if args.renderer == "mitsuba" and (args.tablet_mm or args.pixel_um):
        build_parser().error("arguments --tablet-mm and --pixel-um need --renderer native")
    if args.mesh and args.tablet_mm:
        build_parser().error("arguments --mesh and --tablet-mm: a mesh has its own size")
    if args.renderer != "mitsuba" and (args.spp is not None or args.max_depth is not None):
        build_parser().error("arguments --spp and --max-depth need --renderer mitsuba")
    try:
        if args.renderer == "mitsuba":
            result = _render_mitsuba(args)
        else:
            result = simulate_scan(
                args.out,
                seed=args.seed,
                size=args.size,
                face=args.face,
                preset=args.preset,
                noise=args.noise,
                as_zip=args.zip,
                progress=True,
                mesh=args.mesh,
                physics=args.physics,
                physics_seed=args.physics_seed,
                tablet_mm=args.tablet_mm,
                pixel_size_um=args.pixel_um,
            )
    except (ValueError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # disk full, permissions: nothing half-written is left behind
        print(f"error: cannot write {args.out}: {exc}", file=sys.stderr)
        return 1
    for face, path in result.bundles.items():
        print(f"{face}: {path} ({result.gt_dirs[face]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
