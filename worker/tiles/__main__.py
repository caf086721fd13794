"""CLI: ``python -m worker.tiles MODEL_DIR`` builds MODEL_DIR/tiles/ (docs/tiles.md).

Exit code 2 with a message naming what is missing for a directory that cannot be tiled;
nothing half-written (the old tiles/, if any, stay until the new one is whole).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from worker.tiles.build import TileError, build_tiles


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m worker.tiles", description=__doc__)
    parser.add_argument("model_dir", type=Path, help="a model directory (SCAN_BUNDLE.md)")
    args = parser.parse_args(argv)
    try:
        index = build_tiles(args.model_dir)
    except TileError as exc:
        print(f"tiles: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(index["stats"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
