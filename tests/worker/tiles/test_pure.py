"""The pure parts of worker.tiles: quadtree, pyramids, a tile's mesh."""

from __future__ import annotations

import numpy as np
import pytest

from worker.tiles import quadtree
from worker.tiles.pyramid import halve_height, halve_image, height_level0
from worker.tiles.tile_mesh import tile_mesh


def test_quadtree_covers_the_image_once_per_level():
    w, h, t = 1300, 700, 256
    levels = quadtree.level_count(w, h, t)
    assert levels == 4  # 256·2^3 = 2048 ≥ 1300 > 1024
    for level in range(levels):
        cover = np.zeros((h, w), int)
        for tile in quadtree.tiles_of_level(level, levels, w, h, t):
            x0, y0, x1, y1 = tile.px_rect
            assert x1 - x0 <= t * quadtree.pixel_step(level, levels)
            cover[y0:y1, x0:x1] += 1
        assert (cover == 1).all()


def test_children_partition_their_parent():
    w, h, t = 1300, 700, 256
    levels = quadtree.level_count(w, h, t)
    for level in range(levels - 1):
        for tile in quadtree.tiles_of_level(level, levels, w, h, t):
            x0, y0, x1, y1 = tile.px_rect
            area = sum(
                (c.px_rect[2] - c.px_rect[0]) * (c.px_rect[3] - c.px_rect[1])
                for c in quadtree.children(tile, levels, w, h, t)
            )
            assert area == (x1 - x0) * (y1 - y0)
    last = quadtree.tiles_of_level(levels - 1, levels, w, h, t)[0]
    assert quadtree.children(last, levels, w, h, t) == []


def test_geometric_error_halves_per_level_and_is_in_metres():
    errors = [quadtree.geometric_error_m(lv, 4, 512, 128, 26.8) for lv in range(4)]
    assert errors[-1] == pytest.approx(4 * 26.8e-6)
    assert errors == sorted(errors, reverse=True)
    assert errors[0] == pytest.approx(8 * errors[-1])


def test_quadtree_rejects_empty_images():
    with pytest.raises(ValueError, match="sizes"):
        quadtree.level_count(0, 10, 512)


def test_halve_image_averages_blocks_and_keeps_odd_edges():
    img = np.arange(15, dtype=np.uint8).reshape(3, 5)
    half = halve_image(img)
    assert half.shape == (2, 3)
    assert half[0, 0] == round((0 + 1 + 5 + 6) / 4)
    assert half[1, 2] == 14  # the corner texel has one pixel
    assert half[0, 2] == round((4 + 9) / 2)


def test_halve_height_needs_half_valid_pixels():
    h = np.array([[1.0, 3.0, np.nan, np.nan], [np.nan, 5.0, np.nan, 7.0]], np.float32)
    level = halve_height(height_level0(h)).height_um()
    assert level[0, 0] == pytest.approx(3.0)  # 3 of 4 valid: their mean
    assert np.isnan(level[0, 1])  # 1 of 4 valid


def test_tile_mesh_shares_edges_with_its_neighbour_and_has_a_skirt():
    rng = np.random.default_rng(0)
    heights = rng.uniform(0, 100, (64, 64)).astype(np.float32)
    kw = {"pixel_step": 2, "grid_step": 4, "pixel_size_um": 20.0, "skirt_mm": 0.5}
    left = tile_mesh(heights, (0, 0, 32, 32), **kw)
    right = tile_mesh(heights, (32, 0, 64, 32), **kw)
    surface = lambda m: m.positions_mm[m.positions_mm[:, 2] <= 0]  # noqa: E731
    edge_x = (32 * 2 + 0.5) * 0.02  # texel 32's centre, in mm
    lp = surface(left)
    rp = surface(right)
    shared_l = lp[np.isclose(lp[:, 0], edge_x)]
    shared_r = rp[np.isclose(rp[:, 0], edge_x)]
    assert len(shared_l) == 9 and np.array_equal(
        shared_l[np.argsort(shared_l[:, 1])], shared_r[np.argsort(shared_r[:, 1])]
    )
    # The skirt: vertices 0.5 mm deeper than the surface vertices of the rim.
    assert (left.positions_mm[:, 2] > 0.4).sum() > 0
    assert left.uv.min() > 0 and left.uv.max() < 1.1
    assert left.indices.max() < len(left.positions_mm)


def test_tile_mesh_of_no_data_is_none():
    nan = np.full((16, 16), np.nan, np.float32)
    assert (
        tile_mesh(nan, (0, 0, 16, 16), pixel_step=1, grid_step=4, pixel_size_um=1, skirt_mm=1)
        is None
    )
