"""Fatcross plates: raking light, scans' own normals, detrended curvature, filtered reduction,
the annotated layout, PNG metadata and the one-page PDF."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy import ndimage

from worker.recon.shading_maps import encode_signed8, mean_curvature_per_um, robust_scale
from worker.register.fatcross import (
    FATCROSS_VIEWS,
    FaceMaps,
    curvature_shading,
    detail_curvature_per_um,
    encode_curvature,
    fatcross_layout,
    mean_curvature_from_normals_per_um,
    natural_colour,
    raking_light,
    reduce_image,
    render_orthographic,
)
from worker.register.plates import (
    FACE_LABELS,
    PlateInfo,
    annotated_plate,
    plate_pdf_bytes,
    plate_png_bytes,
)

PX = 20.0  # px/mm in the synthetic renders


def _wedged_surface(shape=(200, 240), *, radius_mm: float | None = None):
    """A render dict of a surface with V-shaped wedges (1 mm wide, 150 µm deep) every 3 mm,
    on a plane or on a cylinder of ``radius_mm`` (the tablet's overall curvature)."""
    rows, cols = shape
    x_mm = (np.arange(cols) + 0.5) / PX
    y_mm = (np.arange(rows) + 0.5) / PX
    gx, gy = np.meshgrid(x_mm, y_mm)
    d = np.abs(((gx + 1.5) % 3.0) - 1.5)  # distance (mm) to the nearest wedge axis
    h = -150.0 * np.clip(1.0 - d / 0.5, 0.0, None)
    if radius_mm is not None:
        xc = gx - gx.mean()
        h = h + 1000.0 * (np.sqrt(radius_mm**2 - xc**2) - radius_mm)
    dy, dx = np.gradient(h, 1000.0 / PX)
    # height is toward the camera (z = −h): the outward normal is (−h_x, −h_y, −1), normalized.
    n = np.stack([-dx, -dy, -np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = np.ones(shape, bool)
    return {
        "rgb": np.full((*shape, 3), 0.7),
        "normals": n,
        "height_um": h,
        "mask": mask,
    }, d


def _local_contrast(img: np.ndarray) -> float:
    lum = img.astype(float).mean(-1)
    return float(np.std(lum - ndimage.uniform_filter(lum, 31)))


def test_raking_light_comes_from_the_upper_left_at_70_degrees():
    l_dir = raking_light()
    assert np.isclose(np.linalg.norm(l_dir), 1.0)
    assert np.isclose(np.degrees(np.arccos(-l_dir[2])), 70.0)
    assert l_dir[0] < 0 and l_dir[1] < 0 and np.isclose(l_dir[0], l_dir[1])
    with pytest.raises(ValueError, match="polar_deg"):
        raking_light(95.0)


def test_raking_light_shows_wedges_that_frontal_light_flattens():
    render, _ = _wedged_surface()
    raking = natural_colour(render)
    frontal = natural_colour(render, light=np.array([0.0, 0.0, -1.0]))
    assert _local_contrast(raking) > 3 * _local_contrast(frontal)
    # A flat face toward the camera is neither black nor burnt out.
    flat = raking[:, 200 // 2].mean()
    assert 100 < flat < 250


def test_curvature_removes_the_tablets_overall_shape():
    render, d = _wedged_surface(radius_mm=8.0)
    grey = curvature_shading(render, px_per_mm=PX)[..., 0].astype(float)
    inner = ndimage.binary_erosion(render["mask"], iterations=40)
    between = (d > 1.0) & inner  # away from any wedge
    on_wedge = (d < 0.05) & inner
    assert abs(np.median(grey[between]) - 128) <= 1
    assert np.percentile(np.abs(grey[between] - 128), 95) <= 2
    # A wedge's bottom is a trough: dark.
    assert np.median(grey[on_wedge]) < 128 - 40
    # Without the band-pass the cylinder tints everything between the wedges.
    k = mean_curvature_per_um(render["height_um"], pixel_size_um=1000 / PX, scale_um=75.0)
    plain = encode_signed8(k, scale=robust_scale(k)).astype(float)
    assert abs(np.median(plain[between]) - 128) >= 6


def test_one_display_range_keeps_a_face_without_signs_grey():
    signs, _ = _wedged_surface()
    rows, cols = signs["mask"].shape
    x = (np.arange(cols) + 0.5) / PX
    h = 0.5 * np.sin(2 * np.pi * x / 0.4)[None, :].repeat(rows, 0)  # 0.5 µm ripples, no sign
    hy, hx = np.gradient(h, 1000.0 / PX)
    n = np.stack([-hx, -hy, -np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    faint = {**signs, "normals": n, "height_um": h}
    k_s, in_s = detail_curvature_per_um(signs, px_per_mm=PX)
    k_f, in_f = detail_curvature_per_um(faint, px_per_mm=PX)
    pooled = robust_scale(np.concatenate([k_s[in_s], k_f[in_f]]))
    shared = encode_curvature(k_f, scale_per_um=pooled)[..., 0].astype(float)
    alone = curvature_shading(faint, px_per_mm=PX)[..., 0].astype(float)
    assert np.percentile(np.abs(shared[in_f] - 128), 95) < 10
    assert np.percentile(np.abs(alone[in_f] - 128), 95) > 60  # its own range stretches it


def test_curvature_from_normals_of_a_sphere_cap_is_one_over_r():
    r_um, pixel_um = 20_000.0, 50.0
    y, x = (np.mgrid[0:201, 0:201] - 100) * pixel_um
    h = np.sqrt(r_um**2 - x**2 - y**2)  # toward the camera: a dome, a ridge everywhere
    hy, hx = np.gradient(h, pixel_um)
    n = np.stack([-hx, -hy, -np.ones_like(h)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    k = mean_curvature_from_normals_per_um(
        n, np.ones(h.shape, bool), pixel_size_um=pixel_um, scale_um=0.0
    )
    assert np.allclose(k[20:-20, 20:-20], 1 / r_um, rtol=0.02)


def test_reduce_image_filters_detail_above_the_output_nyquist():
    # Stripes of period 2.5 px reduced 3×: 0.83 px per period, far above the output's Nyquist.
    x = np.arange(600)
    stripes = (127.5 + 127.5 * np.sin(2 * np.pi * x / 2.5))[None, :].repeat(300, 0)
    img = np.repeat(stripes[..., None], 3, -1).astype(np.uint8)
    reduced = reduce_image(img, (200, 100)).astype(float)
    naive = img[::3, ::3].astype(float)
    assert reduced.shape == (100, 200, 3)
    assert np.std(naive) > 30  # point sampling folds the stripes into a visible beat
    assert np.std(reduced[5:-5, 5:-5]) < 0.1 * np.std(naive)
    assert abs(reduced.mean() - img.mean()) < 3  # the mean survives


def test_render_uses_the_scans_full_resolution_normals():
    box = trimesh.creation.box(extents=(30.0, 20.0, 6.0))
    colours = np.full((len(box.vertices), 4), 200, np.uint8)
    s_um = 50.0
    rows, cols = int(20e3 / s_um), int(30e3 / s_um)
    x_mm = np.arange(cols) * s_um / 1000
    tilt = 0.5 * np.sin(2 * np.pi * x_mm / 2.0)  # ripples of 2 mm the mesh does not have
    n = np.stack(
        [np.broadcast_to(tilt, (rows, cols)), np.zeros((rows, cols)), -np.ones((rows, cols))], -1
    )
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    t = np.eye(4)
    t[:3, 3] = (-15.0, -10.0, 0.0)  # scan pixel (0, 0) at the box's corner
    face = FaceMaps(
        t,
        n,
        np.full((rows, cols, 3), 90, np.uint8),
        np.ones((rows, cols), bool),
        np.full((rows, cols), 3000.0),  # the obverse is 3 mm toward the camera
        s_um,
    )
    plain = render_orthographic(
        box.vertices, box.faces, colours, box.vertex_normals, FATCROSS_VIEWS["o"], px_per_mm=PX
    )
    scans = render_orthographic(
        box.vertices,
        box.faces,
        colours,
        box.vertex_normals,
        FATCROSS_VIEWS["o"],
        px_per_mm=PX,
        faces=[face],
    )
    inner = ndimage.binary_erosion(scans["mask"], iterations=5)
    assert scans["from_scans"][inner].mean() > 0.99
    x_px = (np.arange(scans["mask"].shape[1]) + 0.5) / PX
    want = (0.5 * np.sin(2 * np.pi * x_px / 2.0))[None, :] / np.sqrt(
        1 + (0.5 * np.sin(2 * np.pi * x_px / 2.0))[None, :] ** 2
    )
    got = scans["normals"][..., 0]
    assert np.nanmax(np.abs(got - want)[inner]) < 0.05
    assert np.allclose(scans["rgb"][inner], 90 / 255, atol=0.01)
    # The box's mesh has no ripples: without the scans they are not there to light.
    want_img = np.broadcast_to(want, got.shape)
    assert abs(np.corrcoef(plain["normals"][..., 0][inner], want_img[inner])[0, 1]) < 0.2
    # The reverse view: the scan faces away, so it must not be used there.
    back = render_orthographic(
        box.vertices,
        box.faces,
        colours,
        box.vertex_normals,
        FATCROSS_VIEWS["r"],
        px_per_mm=PX,
        faces=[face],
    )
    assert not back["from_scans"].any()


def _views(px: float = 10.0):
    sizes = {
        "o": (20, 30),
        "te": (6, 30),
        "be": (6, 30),
        "le": (20, 6),
        "re": (20, 6),
        "r": (20, 30),
    }
    rng = np.random.default_rng(0)
    return {
        k: rng.integers(60, 255, (int(h * px), int(w * px), 3), dtype=np.uint8)
        for k, (h, w) in sizes.items()
    }


def test_fatcross_layout_positions():
    views = _views()
    at, (h, w) = fatcross_layout({k: v.shape[:2] for k, v in views.items()}, gap_px=7)
    assert at["te"] == (0, 60 + 7) and at["o"] == (60 + 7, 60 + 7)
    assert at["le"] == (67, 0) and at["re"] == (67, 67 + 300 + 7)
    assert at["be"] == (67 + 200 + 7, 67) and at["r"] == (274 + 60 + 7, 67)
    assert (h, w) == (60 + 200 + 60 + 200 + 21, 60 + 300 + 60 + 14)
    with pytest.raises(ValueError, match="missing"):
        fatcross_layout({"o": (1, 1)}, gap_px=1)


def test_annotated_plate_has_title_labels_scale_caption_licence():
    px = 10.0
    views = _views(px)
    info = PlateInfo("P451806", licence="CC BY 4.0, test", simulated=True)
    plate, boxes = annotated_plate(views, px_per_mm=px, info=info, kind="natural")
    background = plate.max(-1) == 0

    def ink(box):
        x0, y0, x1, y1 = box
        return (~background[y0:y1, x0:x1]).sum()

    for key in ("title", "scale", "scale_label", "caption", "licence", *FACE_LABELS):
        assert ink(boxes[key]) > 10, key
    # Each label sits just above its view and overlaps no view.
    for k in FACE_LABELS:
        lx0, ly0, lx1, ly1 = boxes[k]
        vx0, vy0, vx1, vy1 = boxes[f"view_{k}"]
        assert ly1 <= vy0 and vy0 - ly1 < 2 * 22 and lx0 >= vx0 - 1
        for v in FACE_LABELS:
            bx0, by0, bx1, by1 = boxes[f"view_{v}"]
            assert lx1 <= bx0 or lx0 >= bx1 or ly1 <= by0 or ly0 >= by1, (k, v)
    # Views are pasted unchanged, in CDLI's arrangement.
    x0, y0, x1, y1 = boxes["view_o"]
    assert np.array_equal(plate[y0:y1, x0:x1], views["o"])
    assert boxes["view_te"][3] < y0 and boxes["view_be"][1] > y1 and boxes["view_r"][1] > y1
    assert boxes["view_le"][2] < x0 and boxes["view_re"][0] > x1
    assert boxes["title"][3] < boxes["te"][1]
    # The bar is 1 cm long at 10 px/mm, below the reverse.
    sx0, sy0, sx1, _ = boxes["scale"]
    assert sx1 - sx0 == 100 and sy0 > boxes["view_r"][3]


def test_plate_png_metadata_and_dpi():
    px = 600 / 25.4
    img = np.zeros((50, 80, 3), np.uint8)
    info = PlateInfo("Ḫ 12", licence="CC BY 4.0", simulated=True)
    data = plate_png_bytes(img, px_per_mm=px, info=info, kind="curvature")
    with Image.open(io.BytesIO(data)) as im:
        assert abs(im.info["dpi"][0] - 600) < 0.5
        assert im.text["Title"].startswith("Ḫ 12")
        assert im.text["Copyright"] == "CC BY 4.0"
        assert im.text["Simulated"] == "true"
        assert "SIMULATED SCAN" in im.text["Description"]
        assert "px/mm" in im.text["Scale"]


def test_pdf_is_one_page_at_true_size():
    px = 300 / 25.4
    a = np.zeros((400, 300, 3), np.uint8)
    b = np.full((350, 300, 3), 50, np.uint8)
    data = plate_pdf_bytes([a, b], px_per_mm=px, info=PlateInfo("P1"))
    assert data.startswith(b"%PDF")
    assert len(re.findall(rb"/Type\s*/Page\b", data)) == 1
    box = [float(v) for v in re.search(rb"/MediaBox\s*\[([^\]]+)\]", data).group(1).split()]
    gap = round(5 * px)
    # PDF points are 1/72 inch: the page is the pixels at 300 dpi.
    assert np.isclose(box[2], (600 + gap) / 300 * 72, atol=0.5)
    assert np.isclose(box[3], 400 / 300 * 72, atol=0.5)
    with pytest.raises(ValueError, match="none"):
        plate_pdf_bytes([], px_per_mm=px, info=PlateInfo("P1"))
