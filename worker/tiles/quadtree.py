"""The quadtree over a model's image grid (pure functions, no I/O).

Level 0 is one tile covering the whole image; level l + 1 halves the pixel step of level l,
down to the deepest level L where one texel is one image pixel. A tile (l, x, y) covers the
full-resolution pixel rectangle [x·T·s, (x+1)·T·s) × [y·T·s, (y+1)·T·s) clipped to the
image, with s = 2^(L−l) the level's pixel step and T the texture side in texels; its
children are (l+1, 2x+i, 2y+j) for i, j ∈ {0, 1} that intersect the image. This is the
layout of a tiled image pyramid (the IIIF Image API 3.0 §5.6 `scaleFactors`), here driving
the 3D Tiles quadtree (OGC 3D Tiles 1.1 §"Implicit tiling" uses the same indexing).

Geometric error (3D Tiles 1.1 §"Geometric error"): the spacing of the tile's mesh samples in
metres, mesh_step_px · pixel_size_um · 1e−6; it halves with each level, so it decreases
strictly from the root to the leaves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "Tile",
    "children",
    "geometric_error_m",
    "level_count",
    "mesh_step_px",
    "pixel_step",
    "tiles_of_level",
]


@dataclass(frozen=True)
class Tile:
    """One tile of the quadtree: its level, column, row and full-resolution pixel rectangle
    (x0, y0, x1, y1), half-open."""

    level: int
    x: int
    y: int
    px_rect: tuple[int, int, int, int]


def level_count(width_px: int, height_px: int, texture_px: int) -> int:
    """Number of levels L + 1 so that level 0's one tile of texture_px texels covers the image."""
    if width_px < 1 or height_px < 1 or texture_px < 1:
        raise ValueError(f"sizes must be ≥ 1, got {width_px}×{height_px}, tile {texture_px}")
    return 1 + max(0, math.ceil(math.log2(max(width_px, height_px) / texture_px)))


def pixel_step(level: int, levels: int) -> int:
    """Full-resolution pixels per texel at `level` (of `levels`): 2^(levels − 1 − level)."""
    if not 0 <= level < levels:
        raise ValueError(f"level {level} outside 0 … {levels - 1}")
    return 1 << (levels - 1 - level)


def mesh_step_px(level: int, levels: int, texture_px: int, grid_cells: int) -> int:
    """Full-resolution pixels between two mesh samples at `level` (grid_cells per tile side)."""
    return max(1, pixel_step(level, levels) * texture_px // grid_cells)


def geometric_error_m(
    level: int, levels: int, texture_px: int, grid_cells: int, pixel_size_um: float
) -> float:
    """The tile's geometric error in metres: its mesh sample spacing (see the module doc)."""
    return mesh_step_px(level, levels, texture_px, grid_cells) * pixel_size_um * 1e-6


def _tile(level: int, x: int, y: int, side: int, width_px: int, height_px: int) -> Tile | None:
    x0, y0 = x * side, y * side
    if x < 0 or y < 0 or x0 >= width_px or y0 >= height_px:
        return None
    return Tile(level, x, y, (x0, y0, min(x0 + side, width_px), min(y0 + side, height_px)))


def tiles_of_level(level: int, levels: int, width_px: int, height_px: int, texture_px: int):
    """Every tile of `level`, row by row."""
    side = texture_px * pixel_step(level, levels)
    out = []
    for y in range(-(-height_px // side)):
        for x in range(-(-width_px // side)):
            tile = _tile(level, x, y, side, width_px, height_px)
            if tile is not None:
                out.append(tile)
    return out


def children(tile: Tile, levels: int, width_px: int, height_px: int, texture_px: int):
    """The (up to four) children of `tile` that intersect the image; none at the last level."""
    if tile.level + 1 >= levels:
        return []
    side = texture_px * pixel_step(tile.level + 1, levels)
    out = []
    for j in (0, 1):
        for i in (0, 1):
            child = _tile(tile.level + 1, 2 * tile.x + i, 2 * tile.y + j, side, width_px, height_px)
            if child is not None:
                out.append(child)
    return out
