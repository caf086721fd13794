"""The relighting viewer in a real browser (chromium + SwiftShader) against the real library
service, on the synthetic tablet of synthetic_model.py."""

from __future__ import annotations

import numpy as np

BACKGROUND = np.array([0x1D, 0x1F, 0x24]) / 255  # the viewer's clear colour


def test_viewer_draws_the_model(viewer_page, library, tools):
    page = viewer_page
    px = tools.canvas_pixels(page)
    on_model = np.abs(px - BACKGROUND).sum(axis=-1) > 0.05
    # The 48 × 32 mm face fills most of the framed view (≥ 25 % of the canvas), and is shaded,
    # not flat: its brightness varies across the pillow and the wedges.
    assert on_model.mean() > 0.25, f"only {on_model.mean():.1%} of the canvas shows the model"
    assert px[on_model].mean(axis=-1).std() > 0.02
    assert page.locator("#title").inner_text() == "P999001"
    assert page.locator("#notice").is_hidden()  # every texture the natural mode needs is there


def _wall_brightness(page, library, tools, azimuth_key: str) -> tuple[float, float]:
    """Mean brightness of the groove's left and right walls with a raking preset."""
    page.locator("#viewer").focus()
    page.keyboard.press(azimuth_key)
    tools.settle(page)
    f = library.facts
    px = tools.canvas_pixels(page).mean(axis=-1)
    box = page.locator("#viewer").bounding_box()
    y_mid = sum(f.groove_y_mm) / 2
    walls = []
    for side in (-1, 1):
        values = []
        for dy in np.linspace(-6, 6, 13):
            x_mm = f.groove_x_mm + side * f.groove_half_width_mm / 2
            sx, sy = tools.screen_of(page, [x_mm, y_mid + dy, -1.0])
            values.append(px[round(sy - box["y"]), round(sx - box["x"])])
        walls.append(float(np.mean(values)))
    return walls[0], walls[1]


def test_light_from_one_side_brightens_the_wall_facing_it(viewer_page, library, tools):
    """The groove's left wall faces +x (the right edge of the image), its right wall −x.

    Raking light from the right (preset 3, φ = 90°, SCAN_BUNDLE.md) must light the left wall
    and leave the right one dark, and the opposite from the left (preset 7, φ = 270°). The
    groove exists only in normals.png (the mesh has a vertex every 1.6 mm, the groove is
    1.2 mm wide), so this also checks that relighting uses the full-resolution normal map.
    """
    page = viewer_page
    page.locator("#mode").select_option("clay")
    left, right = _wall_brightness(page, library, tools, "3")
    assert page.locator("#viewer").get_attribute("data-azimuth") == "90.000"
    # walls tilt atan(250/600) = 22.6°: at θ = 75° the lit wall gets cos(75° − 22.6°) = 0.61,
    # the other cos(75° + 22.6°) < 0 → ambient only; a margin of 0.15 is far above 8-bit noise
    assert left > right + 0.15, (left, right)
    left, right = _wall_brightness(page, library, tools, "7")
    assert right > left + 0.15, (left, right)


def test_dragging_the_light_widget_moves_the_light(viewer_page):
    """The widget is the hemisphere seen from the camera, drawn like the image (y down): a drag
    to its right rim is light from the right edge (φ = 90°), to its top rim from the top
    (φ = 180°), and its centre is light from the camera (θ = 0)."""
    page = viewer_page
    box = page.locator("#light-widget").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    r = box["width"] / 2 - 8 * box["width"] / 320  # the disc's radius (8 px margin at 320 px)
    for target, azimuth in (((cx + r, cy), 90), ((cx, cy - r), 180)):
        page.mouse.move(cx - r / 2, cy)
        page.mouse.down()
        page.mouse.move(*target, steps=4)
        page.mouse.up()
        light = page.evaluate("window.hammurabi.viewer.light")
        assert abs(light["azimuthDeg"] - azimuth) < 2, light
        assert light["polarDeg"] > 80, light
    page.mouse.click(cx, cy)
    assert page.evaluate("window.hammurabi.viewer.light")["polarDeg"] < 3


def test_every_shading_mode_renders_differently(viewer_page, tools):
    page = viewer_page
    images = {}
    for mode in [
        "natural",
        "clay",
        "curvature",
        "accessibility",
        "relief",
        "depth",
        "normals",
        "quality",
    ]:
        page.locator("#mode").select_option(mode)
        tools.idle(page)
        assert page.evaluate("window.hammurabi.viewer.shading.mode") == mode
        # every map of the fixture exists: no "missing texture" notice in any mode
        assert page.locator("#notice").is_hidden(), page.locator("#notice").inner_text()
        images[mode] = tools.render_pixels(page)
    on_model = np.abs(images["clay"] - BACKGROUND).sum(axis=-1) > 0.05
    modes = list(images)
    for i, a in enumerate(modes):
        for b in modes[i + 1 :]:
            diff = np.abs(images[a] - images[b])[on_model].mean()
            # identical renderings differ by 0; 8-bit rounding alone stays below 0.004
            assert diff > 0.01, f"{a} and {b} look the same (mean difference {diff:.4f})"


def test_distance_between_picked_points_is_within_one_percent(viewer_page, library, tools):
    """Two mesh vertices 32 mm apart across the pillow: their true 3-D distance is known."""
    page = viewer_page
    f = library.facts
    a = f.mesh_vertex_mm[(160, 80)]  # (8, 16) mm
    b = f.mesh_vertex_mm[(160, 400)]  # (40, 16) mm
    truth = float(np.linalg.norm(np.subtract(a, b)))
    page.locator("#viewer").focus()
    page.keyboard.press("m")
    for p in (a, b):
        x, y = tools.screen_of(page, p)
        page.mouse.click(x, y)
    page.wait_for_function("() => document.getElementById('readout').dataset.distanceMm")
    measured = float(page.locator("#readout").get_attribute("data-distance-mm"))
    assert abs(measured - truth) / truth < 0.01, (measured, truth)
    assert "mm" in page.locator("#readout").inner_text()


def test_height_profile_follows_the_height_map(viewer_page, library, tools):
    """A profile across the groove: one sample per pixel, drawn as a chart."""
    page = viewer_page
    f = library.facts
    y = 16.0
    a, b = [f.groove_x_mm - 4, y, -1.5], [f.groove_x_mm + 4, y, -1.5]
    page.locator("#viewer").focus()
    page.keyboard.press("h")
    for p in (a, b):
        x, yy = tools.screen_of(page, p)
        page.mouse.click(x, yy)
    page.wait_for_selector("#profile-panel:not([hidden]) svg path.line")
    assert page.locator("#readout").inner_text().startswith("Profile:")
    d = page.locator("svg path.line").get_attribute("d")
    assert d.startswith("M") and d.count("L") > 50  # one sample per 100 µm pixel over ~8 mm


def test_permalink_restores_camera_light_and_shading(viewer_page, tools, browser):
    page = viewer_page
    page.locator("#viewer").focus()
    for key in ("5", "ArrowLeft", "ArrowLeft", "r", "p", "e"):
        page.keyboard.press(key)
    tools.settle(page)
    page.locator("#permalink").click()
    link = page.locator("#permalink-text").input_value()
    before = page.evaluate("window.hammurabi.viewer.getState()")
    other = browser.new_page(viewport=page.viewport_size)
    try:
        other.goto(link)
        other.wait_for_function("() => document.getElementById('viewer').dataset.loaded")
        after = other.evaluate("window.hammurabi.viewer.getState()")
    finally:
        other.close()
    assert after["light"] == before["light"]
    assert after["light"]["azimuthDeg"] == 170  # preset 5 (180°) then two steps of −5°
    assert after["shading"]["mode"] == "relief"
    assert after["camera"]["projection"] == "perspective"
    for key in ("position", "target", "up"):
        np.testing.assert_allclose(after["camera"][key], before["camera"][key], atol=1e-4)


def test_switching_models_frees_gpu_memory(viewer_page, library, tools):
    page = viewer_page
    page.locator("#model-select").select_option(str(library.models["v1"]))
    page.wait_for_function(
        "id => document.getElementById('viewer').dataset.loaded === id",
        arg=str(library.models["v1"]),
    )
    page.locator("#mode").select_option("curvature")
    tools.settle(page)
    first = page.evaluate("window.hammurabi.viewer.memory()")
    for label in ("v2", "v1", "v2", "v1"):
        page.locator("#model-select").select_option(str(library.models[label]))
        page.wait_for_function(
            "id => document.getElementById('viewer').dataset.loaded === id",
            arg=str(library.models[label]),
        )
        tools.settle(page)
    last = page.evaluate("window.hammurabi.viewer.memory()")
    # the same model in the same mode holds the same GPU objects: nothing leaked on the way
    assert last == first, (first, last)


def test_screenshot_is_a_png_of_the_chosen_size(viewer_page):
    import io
    from pathlib import Path

    from PIL import Image

    page = viewer_page
    page.locator("#shot-w").fill("640")
    page.locator("#shot-h").fill("400")
    with page.expect_download() as info:
        page.locator("#screenshot").click()
    data = Path(info.value.path()).read_bytes()
    img = Image.open(io.BytesIO(data))
    assert img.format == "PNG" and img.size == (640, 400)
    px = np.asarray(img.convert("RGB"), dtype=float) / 255
    # the shot contains the canvas's view: the 48 × 32 mm face framed in the (portrait) canvas
    # covers ≥ 10 % of a 1.6:1 shot — drawn, not blank
    assert (np.abs(px - BACKGROUND).sum(axis=-1) > 0.05).mean() > 0.1
