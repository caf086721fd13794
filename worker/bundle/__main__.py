"""``python -m worker.bundle validate PATH``: exit 0 and a summary, or exit 2 and every problem."""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence

from worker.bundle.errors import BundleError
from worker.bundle.reader import open_bundle, validate_bundle

EXIT_INVALID = 2
EXIT_INTERNAL = 1


def _summary(path: str) -> str:
    with open_bundle(path) as bundle:
        m = bundle.manifest
        kinds = Counter(f.kind for f in bundle.frames)
        refs = sum(f.target == "reference" for f in bundle.frames)
        listed = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) or "no frames"
        return (
            f"{path}: valid scan bundle v{m.version}, face {m.scan.face}, "
            f"{m.camera.width}×{m.camera.height} px at {m.camera.pixel_size_um:g} µm, "
            f"{m.camera.bit_depth} bit; {len(bundle.frames)} frames ({listed}; {refs} reference)"
        )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m worker.bundle", description="Scan bundle tools (SCAN_BUNDLE.md v1)."
    )
    commands = parser.add_subparsers(dest="command", required=True)
    check = commands.add_parser("validate", help="check a bundle folder or ZIP against the spec")
    check.add_argument("path", help="bundle folder or .zip")
    args = parser.parse_args(argv)

    try:
        problems = validate_bundle(args.path)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # noqa: BLE001 - a bug of ours must still not print a traceback
        print(f"{args.path}: internal error while validating ({type(exc).__name__}: {exc})")
        return EXIT_INTERNAL
    if problems:
        print(f"{args.path}: invalid scan bundle, {len(problems)} problem(s):")
        for problem in problems:
            print(f"  {problem}")
        return EXIT_INVALID
    try:
        print(_summary(args.path))
    except BundleError as exc:  # the bundle changed between the two reads
        print(exc)
        return EXIT_INVALID
    return 0


if __name__ == "__main__":
    sys.exit(main())
