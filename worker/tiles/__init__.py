"""Tiles of a model for view-dependent streaming (issue 19; docs/tiles.md).

`build_tiles(model_dir)` writes `model_dir/tiles/`: IIIF Image API 3.0 level-0 pyramids of
the albedo, the normal map and the height (libvips dzsave), the full-resolution heights as
raw float32 for Range reads, and an OGC 3D Tiles 1.1 quadtree of meshoptimizer-compressed
GLB tiles; `tiles/index.json`, written last, describes them.

Pure parts: `quadtree` (tile rectangles, geometric error), `pyramid` (2×2 averaging),
`tile_mesh` (a tile's grid mesh and skirt), `tile_glb` (encoding); I/O in `iiif` and `build`.
"""

from worker.tiles.build import TileError, build_tiles

__all__ = ["TileError", "build_tiles"]
