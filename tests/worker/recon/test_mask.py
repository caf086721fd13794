"""Tablet mask (worker.recon.mask): a bright tablet on a dark support, with defects."""

import numpy as np
import pytest

from worker.recon.mask import otsu_threshold, tablet_mask


def _scene(rng, rows=120, cols=160):
    """Clay (ρ ≈ 0.35 ± 20 %) inside a rounded rectangle on velvet (ρ ≈ 0.03 ± 20 %)."""
    y, x = np.mgrid[0:rows, 0:cols]
    tablet = (np.abs(x - cols / 2) < 60) & (np.abs(y - rows / 2) < 45)
    albedo = np.where(tablet, 0.35, 0.03) * rng.uniform(0.8, 1.2, (rows, cols))
    return tablet, albedo.astype(np.float32)


def test_otsu_splits_two_populations():
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.normal(0, 1, 1000), rng.normal(10, 1, 1000)])
    assert 3 < otsu_threshold(v) < 7
    with pytest.raises(ValueError, match="values"):
        otsu_threshold(np.ones(10))


def test_mask_is_the_tablet_without_rim_pixels_or_specks():
    rng = np.random.default_rng(1)
    tablet, albedo = _scene(rng)
    albedo[5, 5] = 0.5  # a bright speck on the support (dust)
    albedo[60, 80] = np.nan  # a pixel inside without albedo (hole, filled)
    mask = tablet_mask(albedo)
    assert not mask[5, 5]
    assert mask[60, 80]
    # One rim pixel is eroded: the mask is the tablet minus its 1-px border, nothing else.
    inner = np.zeros_like(tablet)
    inner[1:-1, 1:-1] = tablet[1:-1, 1:-1] & tablet[:-2, 1:-1] & tablet[2:, 1:-1]
    inner &= np.roll(tablet, 1, 1) & np.roll(tablet, -1, 1)
    assert not np.any(mask & ~tablet)
    assert (mask & inner).sum() >= 0.97 * inner.sum()


def test_unmeasured_and_low_support_pixels_are_dropped():
    rng = np.random.default_rng(2)
    tablet, albedo = _scene(rng)
    # A bright support block (a V-block) at the right edge, far below the tablet.
    albedo[:, 150:] = 0.4
    height = np.where(tablet, 1000.0, -3000.0) + rng.normal(0, 5, tablet.shape)
    has_normal = np.ones(tablet.shape, bool)
    has_normal[:, :8] = False  # nothing measured on the left columns
    albedo[:, :8] = 0.4
    mask = tablet_mask(albedo, has_normal=has_normal, height_um=height)
    assert not mask[:, 140:].any()
    assert not mask[:, :8].any()
    assert mask[60, 80]


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match="has_normal"):
        tablet_mask(np.ones((4, 4)), has_normal=np.ones((3, 4), bool))
    with pytest.raises(ValueError, match="brightness"):
        tablet_mask(np.ones(4))


def test_morphology_is_scipy_ndimage_s():
    # The OpenCV helpers must give scipy.ndimage's binary morphology exactly, borders too
    # (outside the image is background for dilation and erosion alike).
    from scipy import ndimage

    from worker.recon.mask import _dilate, _erode, _fill_holes

    rng = np.random.default_rng(3)
    square = np.ones((3, 3), bool)
    for t in range(12):
        a = ndimage.gaussian_filter(rng.random((40 + t, 33)), 1.5) > 0.45 + 0.01 * t
        a[: t % 3] = True  # shapes touching the border
        for it in (1, 2):
            np.testing.assert_array_equal(
                _erode(_dilate(a, it), it), ndimage.binary_closing(a, square, iterations=it)
            )
            np.testing.assert_array_equal(
                _dilate(_erode(a, it), it), ndimage.binary_opening(a, square, iterations=it)
            )
            np.testing.assert_array_equal(
                _erode(a, it), ndimage.binary_erosion(a, square, iterations=it)
            )
        np.testing.assert_array_equal(_fill_holes(a), ndimage.binary_fill_holes(a))
    for a in (np.ones((5, 6), bool), np.zeros((5, 6), bool)):
        np.testing.assert_array_equal(_fill_holes(a), a)


def test_a_support_as_bright_as_the_clay_is_told_apart_by_height():
    # Dark clay (ρ 0.25) on a light V-block (ρ 0.28) 12 mm below it: brightness alone
    # splits noise; the heights show the support around the tablet.
    from worker.recon.mask import tablet_mask

    rng = np.random.default_rng(4)
    rows, cols = 96, 128
    tablet = np.zeros((rows, cols), bool)
    tablet[20:76, 24:104] = True
    albedo = np.where(tablet, 0.25, 0.28) + rng.normal(0, 0.02, (rows, cols))
    y, x = np.mgrid[0:rows, 0:cols]
    height = np.where(tablet, 5700 + 300 * np.sin(x / 9.0), -6600 - 20 * np.abs(x - 64))
    height = height + rng.normal(0, 3, (rows, cols))
    ones = np.ones((rows, cols), bool)
    got = tablet_mask(albedo.astype(np.float32), has_normal=ones, has_height=ones, height_um=height)
    assert got[20:76, 24:104][2:-2, 2:-2].all()  # the tablet less its eroded rim
    assert not got[~tablet].any()  # none of the support


def test_the_height_split_leaves_a_brightness_mask_that_agrees():
    # Clay on black velvet (few fringe heights on it): brightness decides, as before.
    from worker.recon.mask import tablet_mask

    rng = np.random.default_rng(5)
    rows, cols = 96, 128
    tablet = np.zeros((rows, cols), bool)
    tablet[20:76, 24:104] = True
    albedo = np.where(tablet, 0.3, 0.02) + rng.normal(0, 0.005, (rows, cols))
    height = np.where(tablet, 800 + 600 * np.cos(np.mgrid[0:rows, 0:cols][1] / 20.0), np.nan)
    ones = np.ones((rows, cols), bool)
    with_h = tablet_mask(
        albedo.astype(np.float32),
        has_normal=ones,
        has_height=np.isfinite(height),
        height_um=height,
    )
    without = tablet_mask(
        albedo.astype(np.float32), has_normal=ones, has_height=np.isfinite(height)
    )
    np.testing.assert_array_equal(with_h, without)


def _vblock_scene(rng, rows=96, cols=128, pixel_um=143.0):
    """Clay (ρ 0.27) resting in a light V-block (ρ 0.49, brighter than the clay) whose two
    faces rise toward the top and bottom image borders (native random physics seed 1): the
    support's heights overlap the tablet's lower sides, and brightness picks the support."""
    y, x = np.mgrid[0:rows, 0:cols]
    tablet = (np.abs(x - cols / 2) < 44) & (np.abs(y - rows / 2) < 32)
    # Rounded sides: 2 mm on top, falling to −1.7 mm at the silhouette (the side curving
    # under toward the contact).
    d = np.minimum(44 - np.abs(x - cols / 2), 32 - np.abs(y - rows / 2))
    top = 2000.0 - 3700.0 * np.exp(-np.clip(d, 0, None) / 2.0)
    support = -4000.0 + 0.45 * pixel_um * np.abs(y - rows / 2)  # faces at ~24°
    height = np.where(tablet, top, support) + rng.normal(0, 5, (rows, cols))
    albedo = np.where(tablet, 0.27, 0.49) * rng.uniform(0.9, 1.1, (rows, cols))
    return tablet, albedo.astype(np.float32), height.astype(np.float32)


def test_a_v_block_brighter_than_the_clay_is_not_taken_for_tablet():
    rng = np.random.default_rng(6)
    tablet, albedo, height = _vblock_scene(rng)
    ones = np.ones(tablet.shape, bool)
    got = tablet_mask(
        albedo, has_normal=ones, has_height=ones, height_um=height, pixel_size_um=143.0
    )
    assert not got[~tablet].any()  # none of the V-block
    inner = np.zeros_like(tablet)
    inner[20:76, 24:104] = True
    assert got[inner].mean() > 0.99  # the tablet's top and upper sides


def test_a_frame_filling_tablet_with_a_chip_at_the_border_has_no_support():
    # No support in view: a chip's floor lies below its surroundings and reaches the
    # border, but it is a small share of the border; the tablet's border region has no
    # ground above it.
    from worker.recon.mask import _support_below_cliff

    rng = np.random.default_rng(7)
    rows, cols = 96, 128
    y, x = np.mgrid[0:rows, 0:cols]
    height = 500.0 + 2.0 * x + rng.normal(0, 5, (rows, cols))
    height[(x < 20) & (np.abs(y - 48) < 15)] -= 900.0
    ones = np.ones((rows, cols), bool)
    assert _support_below_cliff(height, ones, pixel_size_um=53.6) is None
    # The same tablet in a V-block: found.
    tablet, _, vb = _vblock_scene(rng)
    support = _support_below_cliff(vb, ones, pixel_size_um=143.0)
    assert support is not None and support[~tablet].mean() > 0.97
    # Of the tablet, at most its outermost ring (a rim pixel mixes both, and is eroded).
    from scipy import ndimage

    assert not support[ndimage.binary_erosion(tablet, iterations=1)].any()


def test_dark_clay_on_a_cloth_as_bright_is_found_whole():
    # Dark clay (ρ 0.12, with a darker band across it, as subsurface light and a glossy
    # patch leave it) on a cloth of about the same brightness (ρ 0.10 ± 30 %) 2 mm below:
    # Otsu's threshold on brightness splits the clay's band off with three quarters of the
    # cloth; the heights show the support, and the mask is the whole tablet, none of the
    # cloth (native random physics seed 9).
    rng = np.random.default_rng(9)
    rows, cols = 96, 128
    y, x = np.mgrid[0:rows, 0:cols]
    tablet = (np.abs(x - cols / 2) < 46) & (np.abs(y - rows / 2) < 34)
    clay = np.where(np.abs(x - cols / 2 + 10) < 8, 0.06, 0.12)  # the band reaches the rim
    cloth = 0.10 * (1 + 0.3 * np.sin(x / 3.0) * np.sin(y / 3.0))
    albedo = np.where(tablet, clay, cloth) * rng.uniform(0.95, 1.05, (rows, cols))
    folds = 60.0 * np.sin(x / 17.0 + y / 23.0)
    height = np.where(tablet, 1500.0 + 40 * np.cos(x / 15.0), -800.0 + folds)
    height = height + rng.normal(0, 5, (rows, cols))
    ones = np.ones((rows, cols), bool)
    got = tablet_mask(
        albedo.astype(np.float32),
        has_normal=ones,
        has_height=ones,
        height_um=height.astype(np.float32),
        pixel_size_um=143.0,
    )
    assert not got[~tablet].any()  # none of the cloth
    inner = np.zeros_like(tablet)
    inner[rows // 2 - 32 : rows // 2 + 32, cols // 2 - 44 : cols // 2 + 44] = True
    assert got[inner].all()  # the whole tablet, its dark band too, less its rim


def test_where_brightness_takes_a_minority_of_the_support_it_keeps_its_mask():
    # The same dark clay, on a cloth a little darker (ρ 0.095): brightness now puts less
    # than half of the cloth in the clay's class. The evidence is mixed (neither cue is
    # clearly the better): the mask stands down to brightness less the support the heights
    # found, and takes none of the cloth, though the clay's dark band is left out.
    rng = np.random.default_rng(9)
    rows, cols = 96, 128
    y, x = np.mgrid[0:rows, 0:cols]
    tablet = (np.abs(x - cols / 2) < 46) & (np.abs(y - rows / 2) < 34)
    band = np.abs(x - cols / 2 + 10) < 10
    clay = np.where(band, 0.07, 0.12)
    cloth = 0.095 * (1 + 0.3 * np.sin(x / 3.0) * np.sin(y / 3.0))
    albedo = np.where(tablet, clay, cloth) * rng.uniform(0.95, 1.05, (rows, cols))
    folds = 60.0 * np.sin(x / 17.0 + y / 23.0)
    height = np.where(tablet, 1500.0 + 40 * np.cos(x / 15.0), -800.0 + folds)
    height = height + rng.normal(0, 5, (rows, cols))
    ones = np.ones((rows, cols), bool)
    got = tablet_mask(
        albedo.astype(np.float32),
        has_normal=ones,
        has_height=ones,
        height_um=height.astype(np.float32),
        pixel_size_um=143.0,
    )
    assert not got[~tablet].any()
    assert not got[tablet & band].any()  # brightness left the band out
    assert got[tablet & ~band].mean() > 0.9
