"""The reader's tools on the tablet page (viewer/scholar.js): the trust mode and the ± of
measurements, unsharp masking and the lens, the best light for a region with its eight raking
lights, and sections with their SVG.

Its own library: a face model of P999002 made by synthetic_model.py plus quality maps with a
band the fringes did not see (columns ≥ 360: normals only), a block where fringes and normals
disagree by 80 µm, and a patch the guard filled; its trust assets are made by the worker's own
code (worker/trust_assets.py)."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

TABLET = "P999002"
NORMALS_ONLY_FROM_COL = 360  # x ≥ 36 mm
DISAGREE_BLOCK = (slice(40, 80), slice(60, 120))  # rows 4–8 mm, columns 6–12 mm
GUARD_PATCH = (slice(200, 230), slice(60, 100))
SHOTS = os.environ.get("HAMMURABI_SAVE_SCREENSHOTS")
DOCS_SHOTS = Path(__file__).resolve().parents[3] / "docs" / "screenshots"


def _trust_model_dir(out: Path, server_module) -> None:
    from worker.trust_assets import trust_assets

    server_module.make_model_dir(out, seed=3)
    h = np.load(out / "height.npy")
    rng = np.random.default_rng(0)
    d = rng.normal(0.0, 3.0, h.shape).astype(np.float32)
    d[:, NORMALS_ONLY_FROM_COL:] = np.nan
    d[DISAGREE_BLOCK] = 80.0
    guard = np.zeros(h.shape, np.uint8)
    guard[GUARD_PATCH] = 1
    np.save(out / "quality" / "fringe_disagreement_um.npy", d)
    np.save(out / "quality" / "guard.npy", guard)
    # Four inlier lights: σ_θ ≈ 0.016 rad from the fixture's residuals, so σ_h grows by
    # ~0.16 µm·√n over n pixels of integration in the normals-only band.
    np.save(out / "quality" / "lights_used.npy", np.full(h.shape, 4, np.int16))
    report = json.loads((out / "report.json").read_text())
    for name, data in trust_assets(out, h, report).items():
        (out / name).write_bytes(data)


@pytest.fixture(scope="module")
def trust_library(tmp_path_factory, server_module):
    tmp = tmp_path_factory.mktemp("scholar")
    _trust_model_dir(tmp / "trust_model", server_module)
    lib = server_module.start_library(
        tmp / "lib", extra_models=[("trust", TABLET, "obverse", tmp / "trust_model")]
    )
    lib.sigma = np.load(tmp / "trust_model" / "uncertainty_um.npy")
    yield lib
    lib.stop()


@pytest.fixture
def scholar_page(page, trust_library, tools):
    lib = trust_library
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}")
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want",
        arg=str(lib.models["trust"]),
        timeout=30000,
    )
    tools.settle(page)
    return page


def _shot(page, name: str) -> None:
    """Save the page's stage for the docs (HAMMURABI_SAVE_SCREENSHOTS=docs/screenshots)."""
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        page.locator(".stage").screenshot(path=str(Path(SHOTS) / name))


def _pixel(page, tools, px, point_mm) -> np.ndarray:
    box = page.locator("#viewer").bounding_box()
    sx, sy = tools.screen_of(page, point_mm)
    r, c = round(sy - box["y"]), round(sx - box["x"])
    return px[r - 2 : r + 3, c - 2 : c + 3].reshape(-1, 3).mean(axis=0)


def _hue_distance(rgb, srgb_ref) -> float:
    """Distance between two colours after normalising brightness (the trust colours are lit)."""
    a = np.asarray(rgb) / max(np.sum(rgb), 1e-6)
    b = np.asarray(srgb_ref) / sum(srgb_ref)
    return float(np.abs(a - b).sum())


AGREE_RGB = (0.33, 0.63, 0.42)
DISAGREE_RGB = (0.89, 0.47, 0.13)
NORMALS_RGB = (0.36, 0.55, 0.86)
FILLED_RGB = (0.84, 0.19, 0.56)


def test_trust_mode_shows_where_heights_come_from(scholar_page, tools):
    page = scholar_page
    page.locator("#viewer").focus()
    page.keyboard.press("u")
    tools.settle(page)
    assert page.locator("#viewer").get_attribute("data-mode") == "trust"
    assert page.locator("#notice").is_hidden()
    px = tools.canvas_pixels(page)
    z = -1.0
    samples = {
        "agree": _pixel(page, tools, px, (20.0, 16.0, z)),
        "disagree": _pixel(page, tools, px, (9.0, 6.0, z)),
        "normals": _pixel(page, tools, px, (42.0, 16.0, z)),
        "filled": _pixel(page, tools, px, (8.0, 21.5, z)),
    }
    refs = {
        "agree": AGREE_RGB,
        "disagree": DISAGREE_RGB,
        "normals": NORMALS_RGB,
        "filled": FILLED_RGB,
    }
    for name, rgb in samples.items():
        own = _hue_distance(rgb, refs[name])
        others = min(_hue_distance(rgb, r) for k, r in refs.items() if k != name)
        assert own < others, (name, rgb, own, others)
    legend = page.locator("#trust-legend")
    assert legend.is_visible()
    items = legend.locator("li").all_inner_texts()
    assert len(items) == 5 and "normals only" in items[2]
    # Columns ≥ 360 of 480 rest on the normals: a quarter of the tablet.
    share = float(re.search(r"\(([\d.]+) %\)", items[2]).group(1))
    assert 23 <= share <= 27, items
    _shot(page, "viewer-trust.png")

    page.locator("#trust-layer").select_option("uncertainty")
    tools.settle(page)
    ends = legend.locator(".ends span").all_inner_texts()
    assert ends[0] == "0 µm" and re.fullmatch(r"≥ [\d.]+ µm", ends[1]), ends
    # σ_h grows into the normals-only band, away from the last fringe pixel: brighter ramp.
    px = tools.canvas_pixels(page)
    near = _pixel(page, tools, px, (36.5, 16.0, z)).sum()
    far = _pixel(page, tools, px, (46.0, 16.0, z)).sum()
    assert far > near + 0.1, (near, far)
    _shot(page, "viewer-trust-uncertainty.png")
    assert "tl=uncertainty" in page.evaluate("() => window.hammurabi.ui.permalinkUrl()")


def _click_points(page, tools, key, points_mm):
    page.locator("#viewer").focus()
    page.keyboard.press(key)
    for p in points_mm:
        page.mouse.click(*tools.screen_of(page, p))


def test_distances_and_profiles_carry_their_uncertainty(scholar_page, tools, trust_library):
    page = scholar_page
    readout = page.locator("#readout")
    pm = {}
    for label, (a, b) in {
        # Mirror images on the symmetric pillow: the same lengths and slopes, so the same
        # share from the grid; only the heights' σ differs.
        "fringes": ((2.0, 16.0, -1.0), (10.0, 16.0, -1.0)),
        "normals": ((46.0, 16.0, -1.0), (38.0, 16.0, -1.0)),
    }.items():
        _click_points(page, tools, "m", [a, b])
        page.wait_for_function(
            "() => document.getElementById('readout').dataset.uncertaintyMm !== undefined"
        )
        assert "±" in readout.inner_text()
        pm[label] = float(readout.get_attribute("data-uncertainty-mm"))
        page.keyboard.press("Escape")
    # Both ± include the grid's half-pixel ends (0.1 mm pixels: ~0.1 mm); where the heights
    # rest on the normals alone the heights' share is larger.
    assert pm["normals"] > pm["fringes"] + 0.001 > 0.001, pm

    _click_points(page, tools, "h", [(30.0, 16.0, -1.0), (47.0, 16.0, -1.0)])
    page.wait_for_function("() => !document.getElementById('profile-panel').hidden")
    band = page.locator("#profile-chart path.band")
    assert band.count() == 1
    assert band.get_attribute("d").count("Z") == 1
    assert "heights ±" in readout.inner_text()
    # σ along the line, from the page, agrees with the asset: the largest σ_h on row 160
    # (y = 16 mm) between columns 300 and 470, interpolated as the page does.
    row = trust_library.sigma[160].astype(np.float64)
    cols = np.linspace(300, 470, 171)
    sigma_top = float(np.nanmax(np.interp(cols, np.arange(row.size), row)))
    text = readout.inner_text()
    top = float(re.search(r"up to ([\d.]+) µm", text).group(1))
    assert top == pytest.approx(sigma_top, rel=0.1), (text, sigma_top)
    # For the docs: a short line in the normals-only band, where the band is wide enough
    # to see at the chart's scale (the tool is still on: two more clicks).
    for p in [(44.5, 16.0, -1.0), (47.5, 16.0, -1.0)]:
        page.mouse.click(*tools.screen_of(page, p))
    page.wait_for_function(
        "() => document.getElementById('readout').textContent.startsWith('Profile: 3.0')"
    )
    _shot(page, "viewer-profile-band.png")
    page.keyboard.press("Escape")


def test_lens_shows_another_mode_inside_a_movable_circle(scholar_page, tools):
    page = scholar_page
    page.locator("#mode").select_option("clay")
    tools.settle(page)
    plain = tools.canvas_pixels(page)
    page.locator("#lens-mode").select_option("trust")
    page.locator("#lens-on").check()
    tools.settle(page)
    lens = page.evaluate("() => window.hammurabi.viewer.enhance.lens")
    assert lens["mode"] == "trust"
    ring = page.locator("#lens-ring")
    assert ring.is_visible()
    box = page.locator("#viewer").bounding_box()
    # Move the lens by dragging its ring onto the normals-only band.
    target = tools.screen_of(page, (42.0, 16.0, -1.0))
    page.mouse.move(box["x"] + lens["x"], box["y"] + lens["y"])
    page.mouse.down()
    page.mouse.move(*target, steps=5)
    page.mouse.up()
    tools.settle(page)
    lens = page.evaluate("() => window.hammurabi.viewer.enhance.lens")
    assert abs(box["x"] + lens["x"] - target[0]) < 2 and abs(box["y"] + lens["y"] - target[1]) < 2
    px = tools.canvas_pixels(page)
    inside = _pixel(page, tools, px, (42.0, 16.0, -1.0))
    assert _hue_distance(inside, NORMALS_RGB) < _hue_distance(inside, AGREE_RGB)
    # Outside the circle the clay render is unchanged.
    far = _pixel(page, tools, px, (8.0, 16.0, -1.0))
    assert np.abs(far - _pixel(page, tools, plain, (8.0, 16.0, -1.0))).max() < 0.02
    assert page.locator("#trust-legend").is_visible()  # the lens shows trust: its legend too
    _shot(page, "viewer-lens.png")
    # A screenshot (viewer.screenshot) draws the lens where it is on the canvas, at any size:
    # at twice the canvas' size, twice as far from the corner.
    w, h = round(box["width"]), round(box["height"])
    shot = tools.render_pixels(page, 2 * w, 2 * h)
    c = shot[
        round(2 * lens["y"]) - 3 : round(2 * lens["y"]) + 4,
        round(2 * lens["x"]) - 3 : round(2 * lens["x"]) + 4,
    ]
    centre = c.reshape(-1, 3).mean(axis=0)
    assert _hue_distance(centre, NORMALS_RGB) < _hue_distance(centre, AGREE_RGB), centre
    edge = shot[round(2 * lens["y"]), round(2 * (lens["x"] - 1.3 * lens["radius"]))]
    assert _hue_distance(edge, NORMALS_RGB) > 0.1, edge  # outside the lens: clay
    page.locator("#lens-on").uncheck()
    tools.settle(page)
    assert page.evaluate("() => window.hammurabi.viewer.enhance.lens") is None


def _detail(page, tools, library_facts):
    """Brightness contrast across the groove's walls in a clay render (the wedge's edges)."""
    px = tools.canvas_pixels(page).mean(axis=-1)
    f = library_facts
    box = page.locator("#viewer").bounding_box()
    y = sum(f.groove_y_mm) / 2
    xs = np.linspace(f.groove_x_mm - 1.5, f.groove_x_mm + 1.5, 31)
    values = []
    for x in xs:
        sx, sy = tools.screen_of(page, (x, y, -1.0))
        values.append(px[round(sy - box["y"]), round(sx - box["x"])])
    return float(np.ptp(values))


def test_unsharp_masking_of_normals_and_luminance_sharpens_the_wedges(
    scholar_page, tools, trust_library
):
    page = scholar_page
    page.locator("#mode").select_option("clay")
    page.locator("#viewer").focus()
    page.keyboard.press("7")  # raking light from the left of the view
    tools.settle(page)
    base = _detail(page, tools, trust_library.facts)
    for slider, value in (("#unsharp-normals", "3"), ("#unsharp-luma", "3")):
        page.locator(slider).fill(value)
        tools.settle(page)
        sharp = _detail(page, tools, trust_library.facts)
        assert sharp > base * 1.15, (slider, base, sharp)
        page.locator(slider).fill("0")
        tools.settle(page)
    page.locator("#unsharp-normals").fill("2")
    tools.settle(page)
    _shot(page, "viewer-unsharp.png")
    page.locator("#unsharp-normals").fill("0")


def test_best_light_for_a_region_rakes_across_its_wedges(scholar_page, tools, trust_library):
    page = scholar_page
    f = trust_library.facts
    page.locator("#region-mm").fill("2")
    page.locator("#viewer").focus()
    page.keyboard.press("w")
    page.mouse.click(*tools.screen_of(page, (f.groove_x_mm, sum(f.groove_y_mm) / 2, -1.0)))
    strip = page.locator("#light-strip")
    strip.wait_for(state="visible")
    # The groove runs along y: the light of most contrast comes across it, from ±x
    # (azimuth 90° or 270°).
    azimuth = float(strip.get_attribute("data-azimuth"))
    assert min(abs(azimuth - 90), abs(azimuth - 270)) <= 10, azimuth
    light = page.evaluate("() => window.hammurabi.viewer.light")
    assert abs(light["azimuthDeg"] - azimuth) < 0.01 and not light["follow"]
    cells = page.locator("#light-strip-cells canvas")
    assert cells.count() == 8
    _shot(page, "viewer-best-light.png")
    third = cells.nth(2)
    want = float(third.get_attribute("data-azimuth"))
    third.click()
    light = page.evaluate("() => window.hammurabi.viewer.light")
    assert abs(light["azimuthDeg"] - want) < 0.01

    # A rectangle between two clicks: 3 × 12 mm around the groove = 30 × 120 pixels of 0.1 mm.
    page.locator("#light-strip-close").click()
    page.locator("#region-shape").select_option("rectangle")
    page.locator("#viewer").focus()
    page.keyboard.press("w")  # off
    page.keyboard.press("w")  # on, as a rectangle
    for p in [(f.groove_x_mm - 1.5, 10.0, -1.0), (f.groove_x_mm + 1.5, 22.0, -1.0)]:
        page.mouse.click(*tools.screen_of(page, p))
    strip.wait_for(state="visible")
    assert 3000 <= int(strip.get_attribute("data-normals")) <= 4200
    azimuth = float(strip.get_attribute("data-azimuth"))
    assert min(abs(azimuth - 90), abs(azimuth - 270)) <= 10, azimuth
    page.keyboard.press("Escape")


def test_section_outline_and_svg(scholar_page, tools, trust_library):
    page = scholar_page
    a, b = (5.0, 16.0, -1.0), (43.0, 16.0, -1.0)
    _click_points(page, tools, "x", [a, b])
    panel = page.locator("#section-panel")
    panel.wait_for(state="visible")
    width = float(panel.get_attribute("data-width-mm"))
    # A face model is a height field: the obverse view's plane cuts it along the line, from
    # one picked point to the other... and on to the rims of the 48 mm face.
    assert 47.0 <= width <= 48.5, width
    depth = float(panel.get_attribute("data-depth-mm"))
    assert 1.0 < depth < 3.0, depth  # the 2 mm pillow
    # Cut from height.npy, not the decimated mesh (test_browser_scholar_whole.py compares it).
    assert panel.get_attribute("data-source") == "heights"
    # One cut through a height field: one polyline (the triangles' segments joined).
    assert page.locator("#section-readout").inner_text().startswith("1 outline,")
    assert page.locator("#section-chart svg path").count() == 1
    _shot(page, "viewer-section.png")
    with page.expect_download() as dl:
        page.locator("#section-svg").click()
    svg = Path(dl.value.path()).read_text()
    w_mm = float(re.search(r'width="([\d.]+)mm"', svg).group(1))
    assert w_mm == pytest.approx(width * 1.16, rel=0.02)  # 8 % margin each side
    assert "P999002" in svg and "scalebar" in svg
    page.locator("#section-close").click()


def test_lens_and_enhancements_come_back_from_the_permalink(scholar_page, tools, trust_library):
    page = scholar_page
    page.locator("#unsharp-normals").fill("1.5")
    page.locator("#lens-on").check()
    tools.settle(page)
    url = page.evaluate("() => window.hammurabi.ui.permalinkUrl()")
    assert "un=1.5" in url and "lz=trust" in url
    lens = page.evaluate("() => window.hammurabi.viewer.enhance.lens")
    page.goto("about:blank")
    page.goto(url)
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want",
        arg=str(trust_library.models["trust"]),
        timeout=30000,
    )
    tools.settle(page)
    back = page.evaluate("() => window.hammurabi.viewer.enhance")
    assert back["normalUnsharp"] == 1.5 and back["lens"] == lens
    assert page.locator("#lens-on").is_checked() and page.locator("#lens-ring").is_visible()
    # A screenshot says how it was enhanced (its PNG Description).
    from PIL import Image

    page.locator("#shot-w").fill("320")
    page.locator("#shot-h").fill("200")
    with page.expect_download() as dl:
        page.locator("#screenshot").click()
    text = Image.open(dl.value.path()).text
    assert "normals unsharp-masked (k = 1.5, r = 8 px); lens: trust" in text["Description"], text


def _slabs(model_dir: Path) -> None:
    """A whole tablet of two 18 × 30 × 4 mm slabs side by side (nodes obverse, reverse)."""
    import trimesh

    scene = trimesh.Scene()
    for name, x in (("obverse", -11.0), ("reverse", 11.0)):
        slab = trimesh.creation.box(extents=(18.0, 30.0, 4.0))
        slab.apply_translation((x, 0.0, 0.0))
        scene.add_geometry(slab, node_name=name, geom_name=name)
    model_dir.mkdir(parents=True)
    (model_dir / "model.glb").write_bytes(scene.export(file_type="glb"))
    (model_dir / "report.json").write_text(json.dumps({"scans": ["obverse", "reverse"]}))


def test_section_through_a_whole_tablet_cuts_its_shown_faces(
    browser, tmp_path_factory, server_module, tools
):
    tmp = tmp_path_factory.mktemp("slabs")
    lib = server_module.start_library(tmp / "lib")
    try:
        _slabs(tmp / "whole")
        model = lib.add_tablet_model("P999003", tmp / "whole")
        context = browser.new_context(viewport={"width": 960, "height": 600}, accept_downloads=True)
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{lib.url}/tablet.html?id={lib.tablets['P999003']}")
        page.wait_for_function(
            "want => document.getElementById('viewer').dataset.loaded === want",
            arg=str(model),
            timeout=30000,
        )
        tools.settle(page)
        panel = page.locator("#section-panel")
        _click_points(page, tools, "x", [(-15.0, 0.0, -2.0), (15.0, 0.0, -2.0)])
        panel.wait_for(state="visible")
        # Two closed rectangles: 40 mm from the left slab's rim to the right one's, 4 mm deep.
        assert page.locator("#section-readout").inner_text().startswith("2 outlines,")
        assert float(panel.get_attribute("data-width-mm")) == pytest.approx(40.0, abs=0.01)
        assert float(panel.get_attribute("data-depth-mm")) == pytest.approx(4.0, abs=0.01)
        page.locator("#section-close").click()
        page.locator("#faces input[data-face='reverse']").uncheck()
        tools.settle(page)
        # The tool stays on (as the distance tool does): two more clicks, another section.
        for p in [(-15.0, 0.0, -2.0), (-5.0, 0.0, -2.0)]:
            page.mouse.click(*tools.screen_of(page, p))
        panel.wait_for(state="visible")
        assert page.locator("#section-readout").inner_text().startswith("1 outline,")
        assert float(panel.get_attribute("data-width-mm")) == pytest.approx(18.0, abs=0.01)
        # These faces have no normals.png: the best light says why it cannot help.
        page.locator("#section-close").click()
        page.locator("#viewer").focus()
        page.keyboard.press("w")
        page.mouse.click(*tools.screen_of(page, (-11.0, -5.0, -2.0)))
        assert "no normals.png" in page.locator("#readout").inner_text()
        context.close()
        assert not errors, errors
    finally:
        lib.stop()
