"""A small procedurally generated face (worker.simulate.large_face) and its tiles."""

from __future__ import annotations

import pytest

from worker.simulate.large_face import write_large_face
from worker.tiles import build_tiles

# Three levels of 512-texel tiles, a partial column and row at the right and bottom edges.
WIDTH_PX, HEIGHT_PX = 1180, 900


@pytest.fixture(scope="session")
def tiled_face(tmp_path_factory):
    """(model directory, index.json dict, progress reports) of a tiled 1180 × 900 px face."""
    model_dir = tmp_path_factory.mktemp("tiles") / "face"
    write_large_face(model_dir, width_px=WIDTH_PX, height_px=HEIGHT_PX, seed=3)
    reports: list[tuple[str, float]] = []
    index = build_tiles(model_dir, progress=lambda s, f: reports.append((s, f)))
    return model_dir, index, reports
