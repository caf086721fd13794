"""Signs linked to the transliteration, in a real browser: a scholar signs in, draws a region
around a sign on the model, ties it to a sign of the ATF, finds it by search and highlights it
by clicking the sign; a reader who is not signed in sees the annotations but no form.

Its own library instance (annotations and an ATF text change what the shared one shows).
Set HAMMURABI_SAVE_SCREENSHOTS=docs/screenshots to keep the screenshots."""

from __future__ import annotations

import os
from pathlib import Path

import httpx
import numpy as np
import pytest

ATF = "@obverse\n1. a-na {d}utu\n2. qi2-bi2-ma\n@reverse\n1. um-ma lugal-ma"
# A square around the deep crossing of the synthetic model's wedges (x 24 mm, y 6 mm).
SQUARE_MM = [(21.0, 3.5), (27.0, 3.5), (27.0, 9.0), (21.0, 9.0)]
OUTLINE = np.array([0x35, 0xD0, 0xFF]) / 255


@pytest.fixture(scope="module")
def own_library(server_module, tmp_path_factory):
    lib = server_module.start_library(tmp_path_factory.mktemp("annotations"))
    tablet_id = lib.tablets["P999001"]
    with httpx.Client(base_url=lib.url) as http:
        login = {"email": server_module.STAFF_EMAIL, "password": server_module.STAFF_PASSWORD}
        assert http.post("/api/v1/auth/login", json=login).status_code == 200
        assert http.patch(f"/api/v1/tablets/{tablet_id}", json={"atf": ATF}).status_code == 200
    yield lib
    lib.stop()


def _save(page, name: str) -> None:
    folder = os.environ.get("HAMMURABI_SAVE_SCREENSHOTS")
    if folder:
        page.screenshot(path=str(Path(folder) / name))


def _share(px: np.ndarray, colour: np.ndarray) -> float:
    return float(np.mean(np.all(np.abs(px - colour) < 0.12, axis=-1)))


def _tinted(px: np.ndarray) -> float:
    """Share of pixels tinted by the highlight (magenta: blue above green, unlike clay)."""
    return float(np.mean(px[..., 2] - px[..., 1] > 0.04))


def _open(page, library, tools) -> None:
    tools.open_tablet(page, library, model="v2")
    page.wait_for_selector("#transliteration button.sign")


def test_a_scholar_ties_a_region_to_a_sign_and_finds_it_again(
    page, own_library, server_module, tools
):
    library = own_library
    page.goto(f"{library.url}/staff.html")
    page.locator("#email").fill(server_module.STAFF_EMAIL)
    page.locator("#password").fill(server_module.STAFF_PASSWORD)
    page.locator("#login-form button").click()
    page.wait_for_selector("#work:not([hidden])")
    _open(page, library, tools)

    signs = page.locator("#transliteration button.sign")
    assert signs.all_text_contents()[:4] == ["a", "na", "{d}", "utu"]
    page.locator("#annotation-new").click()
    assert page.locator("#annotation-draw").get_attribute("aria-pressed") == "true"
    # Too few points: said in the form, nothing sent.
    page.locator("#annotation-reference").fill("o 1 3")
    page.locator("#annotation-save").click()
    assert "at least 3 points" in page.locator("#annotation-error").text_content()

    for x, y in SQUARE_MM:
        sx, sy = tools.screen_of(page, (x, y, 0.0))
        page.mouse.click(sx, sy)
    assert page.evaluate("() => window.hammurabi.annotations.state.draft.length") == 4
    assert "4 points" in page.locator("#annotation-status").text_content()

    # A line the transliteration does not have: the server's 422 names it.
    page.locator("#annotation-reference").fill("")
    page.locator("#annotation-reference").press_sequentially("o 9 1")  # keys, not shortcuts
    page.locator("#annotation-save").click()
    page.wait_for_selector("#annotation-error:not([hidden])")
    assert "the obverse has no line '9'" in page.locator("#annotation-error").text_content()

    # Clicking the sign in the transliteration fills the reference.
    page.locator('#transliteration button.sign[data-ref="o 1 3"]').click()
    assert page.locator("#annotation-reference").input_value() == "o 1 3"
    page.locator("#annotation-reading").fill("{d}")
    page.locator("#annotation-comment").fill("divine determinative before Utu")
    page.locator("#annotation-save").click()
    page.wait_for_selector('#annotation-list li[data-ref="o 1 3"]')
    assert page.locator("#annotation-form").is_hidden()
    item = page.locator('#annotation-list li[data-ref="o 1 3"]')
    assert "version 2" in item.text_content() and "divine determinative" in item.text_content()
    assert "annotated" in page.locator('button.sign[data-ref="o 1 3"]').get_attribute("class")

    # Saved as drawn: the region's points are where we clicked (mm), on this model version.
    stored = page.evaluate("() => window.hammurabi.annotations.state.items[0]")
    assert stored["modelId"] == library.models["v2"]
    got = np.array(stored["polygonMm"])[:, :2]
    assert np.allclose(got, np.array(SQUARE_MM), atol=0.3), got
    assert stored["target"][1]["selector"][1]["value"].startswith("xywh=pixel:2")

    # The new annotation is highlighted on the model (filled); clicking the sign again clears it.
    tools.settle(page)
    cx, cy = tools.screen_of(page, (24.0, 6.25, 0.0))
    box = page.locator("#viewer").bounding_box()
    px = tools.canvas_pixels(page)
    r, c = int(cy - box["y"]), int(cx - box["x"])
    patch = px[r - 15 : r + 15, c - 15 : c + 15]
    _save(page, "annotations.png")
    # The fill is translucent magenta over clay: red up, green down against the clay.
    assert _tinted(patch) > 0.5, patch.mean(axis=(0, 1))
    page.locator('#transliteration button.sign[data-ref="o 1 3"]').click()
    tools.settle(page)
    patch = tools.canvas_pixels(page)[r - 15 : r + 15, c - 15 : c + 15]
    assert _tinted(patch) < 0.05
    page.locator('#transliteration button.sign[data-ref="o 1 3"]').click()

    # Search: by reading, by reference; a miss lists nothing.
    search = page.locator("#annotation-search")
    for q, expected in (("DETERMINATIVE", 1), ("o 1", 1), ("o 1 3", 1), ("r 1", 0), ("x", 0)):
        search.fill(q)
        page.wait_for_function(
            "q => document.getElementById('annotation-count').textContent.includes(q)", arg=q
        )
        assert page.locator("#annotation-list li").count() == expected, q
    search.fill("")
    page.wait_for_function(
        "() => !document.getElementById('annotation-count').textContent.includes('matching')"
    )

    # The author edits the comment (the region stays), then a second annotation is deleted.
    page.locator('#annotation-list li[data-ref="o 1 3"] button.edit').click()
    assert page.locator("#annotation-reference").input_value() == "o 1 3"
    page.locator("#annotation-comment").fill("determinative, clear")
    page.locator("#annotation-save").click()
    page.wait_for_function(
        "() => document.getElementById('annotation-list').textContent.includes('clear')"
    )
    edited = page.evaluate("() => window.hammurabi.annotations.state.items[0]")
    assert (
        edited["comment"] == "determinative, clear" and edited["polygonMm"] == stored["polygonMm"]
    )
    page.locator("#annotation-new").click()
    for x, y in [(5.0, 5.0), (8.0, 5.0), (8.0, 8.0)]:
        sx, sy = tools.screen_of(page, (x, y, 0.0))
        page.mouse.click(sx, sy)
    page.locator("#annotation-reference").fill("o 2 2")
    page.locator("#annotation-save").click()
    page.wait_for_selector('#annotation-list li[data-ref="o 2 2"]')
    page.once("dialog", lambda dialog: dialog.accept())
    page.locator('#annotation-list li[data-ref="o 2 2"] button.delete').click()
    page.wait_for_selector('#annotation-list li[data-ref="o 2 2"]', state="detached")
    assert page.locator("#annotation-list li").count() == 1

    # The older version does not show this version's region, but lists it.
    page.locator("#model-select").select_option(str(library.models["v1"]))
    page.wait_for_function(
        f"() => document.getElementById('viewer').dataset.loaded === '{library.models['v1']}'"
    )
    item = page.locator('#annotation-list li[data-ref="o 1 3"]')
    assert "not shown" in item.text_content()
    tools.settle(page)
    patch = tools.canvas_pixels(page)[r - 15 : r + 15, c - 15 : c + 15]
    assert _tinted(patch) < 0.05 and _share(patch, OUTLINE) < 0.01


def test_a_reader_not_signed_in_sees_annotations_but_no_form(browser, own_library, tools):
    context = browser.new_context(viewport={"width": 960, "height": 600})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    # An anonymous reader is not an error: no request of the page may fail (a 401 from
    # /auth/me was logged in the console on every anonymous page view).
    failed: list[str] = []
    page.on("response", lambda r: failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)
    try:
        with httpx.Client(base_url=own_library.url) as http:
            http.post(
                "/api/v1/auth/login",
                json={"email": "curator@example.org", "password": "clay tablets are patient"},
            )
            created = http.post(
                f"/api/v1/models/{own_library.models['v2']}/annotations",
                json={
                    "reference": "o 2 1",
                    "reading": "qi2",
                    "comment": '<img src=x onerror="window.__xss = 1">',  # text, never HTML
                    "polygon_mm": [[5, 5, 0], [9, 5, 0], [9, 9, 0]],
                },
            )
            assert created.status_code == 201, created.text
        _open(page, own_library, tools)
        page.wait_for_selector('#annotation-list li[data-ref="o 2 1"]')
        assert page.locator("#annotation-login").is_visible()
        assert page.locator("#annotation-new").is_hidden()
        assert page.locator("#annotation-list button.delete").count() == 0
        comment = page.locator('#annotation-list li[data-ref="o 2 1"] .comment')
        assert comment.text_content() == '<img src=x onerror="window.__xss = 1">'
        assert page.locator("#annotation-list img").count() == 0
        assert page.evaluate("() => window.__xss === undefined")
        page.locator('#annotation-list li[data-ref="o 2 1"] button.ref').click()
        assert page.evaluate("() => window.hammurabi.annotations.state.highlighted") == "o 2 1"
        pressed = page.locator('#transliteration button.sign[aria-pressed="true"]')
        assert pressed.all_text_contents() == ["qi2"]
        _save(page, "annotations-reader.png")
    finally:
        context.close()
    assert not errors, errors
    assert not failed, failed


def _two_face_model(out: Path) -> None:
    """A whole-tablet model of two flat 12 × 10 mm faces side by side: "obverse" at the
    origin, "reverse" 14 mm to the right; 250 µm pixels, so pixel (r, c) is at (c/4, r/4) mm
    of its face."""
    import io
    import json

    from PIL import Image

    from worker.register.io import face_asset_dir, write_output_dir
    from worker.register.merge import grid_mesh, scene_glb

    rows, cols = 40, 48
    flat = np.zeros((rows, cols))
    mask = np.ones((rows, cols), bool)
    meshes, moves, files = {}, {}, {}
    for k, (name, colour) in enumerate((("obverse", (190, 150, 100)), ("reverse", (150, 120, 90)))):
        meshes[name] = grid_mesh(
            flat, mask, np.full((rows, cols, 3), colour, np.uint8), pixel_size_um=250.0
        )
        moves[name] = np.eye(4)
        moves[name][0, 3] = 14.0 * k
        rgba = np.zeros((rows, cols, 4), np.uint8)
        rgba[...] = (128, 128, 0, 255)  # n = (0, 0, -1): toward the camera
        buf = io.BytesIO()
        Image.fromarray(rgba).save(buf, format="PNG")
        files[f"{face_asset_dir(name)}/normals.png"] = buf.getvalue()
    files["model.glb"] = scene_glb(meshes, moves)
    files["report.json"] = json.dumps({"scans": list(meshes)}).encode()
    write_output_dir(out, files)


def _draw(page, tools, points_mm) -> None:
    page.locator("#annotation-new").click()
    for x, y in points_mm:
        sx, sy = tools.screen_of(page, (x, y, 0.0))
        page.mouse.click(sx, sy)


def test_on_the_whole_tablet_the_region_is_also_on_its_face_image_grid(
    page, own_library, server_module, tools, tmp_path
):
    _two_face_model(tmp_path / "two-faces")
    model_id = own_library.add_tablet_model("P999003", tmp_path / "two-faces")
    page.goto(f"{own_library.url}/staff.html")
    page.locator("#email").fill(server_module.STAFF_EMAIL)
    page.locator("#password").fill(server_module.STAFF_PASSWORD)
    page.locator("#login-form button").click()
    page.wait_for_selector("#work:not([hidden])")
    page.goto(f"{own_library.url}/tablet.html?id=P999003")
    page.wait_for_function(
        f"() => document.getElementById('viewer').dataset.loaded === '{model_id}'",
        timeout=30000,
    )
    tools.settle(page)
    assert page.evaluate("() => window.hammurabi.viewer.partNames()") == ["obverse", "reverse"]

    square = [(3.0, 3.0), (8.0, 3.0), (8.0, 7.0), (3.0, 7.0)]
    _draw(page, tools, square)
    page.locator("#annotation-reference").fill("o 1 1")
    page.locator("#annotation-save").click()
    page.wait_for_selector('#annotation-list li[data-ref="o 1 1"]')
    (on_face,) = page.evaluate("() => window.hammurabi.annotations.state.items")
    assert on_face["modelId"] == model_id and on_face["face"] == "tablet"
    assert on_face["imageFace"] == "obverse"
    expected_px = np.array(square) * 4.0  # 250 µm pixels
    assert np.allclose(np.array(on_face["polygonPx"]), expected_px, atol=0.3), on_face
    image = on_face["target"][1]["source"]["id"]
    assert image.endswith(f"/models/{model_id}/assets/faces/obverse/normals.png")

    # Over the gap onto the other face: no single image grid, the region in mm only.
    _draw(page, tools, [(9.0, 3.0), (17.0, 3.0), (17.0, 7.0)])
    page.locator("#annotation-reference").fill("o 1 2")
    page.locator("#annotation-save").click()
    page.wait_for_selector('#annotation-list li[data-ref="o 1 2"]')
    across = page.evaluate("() => window.hammurabi.annotations.state.items[1]")
    assert across["polygonPx"] is None and len(across["target"]) == 1
    assert np.allclose(np.array(across["polygonMm"])[:, :2], [(9, 3), (17, 3), (17, 7)], atol=0.3)


def test_a_model_licence_set_by_staff_is_in_the_citation(browser, own_library, tools):
    """Issue 18: a model version's own licence and credit reach what a reader copies."""
    model_id = own_library.models["v1"]
    licence = "https://creativecommons.org/licenses/by-sa/4.0/"
    with httpx.Client(base_url=own_library.url) as http:
        login = {"email": "curator@example.org", "password": "clay tablets are patient"}
        assert http.post("/api/v1/auth/login", json=login).status_code == 200
        changed = http.patch(
            f"/api/v1/models/{model_id}",
            json={"licence": licence, "attribution": "Scan by the Test Museum lab"},
        )
        assert changed.status_code == 200, changed.text
    context = browser.new_context(viewport={"width": 960, "height": 600})
    page = context.new_page()
    try:
        tools.open_tablet(page, own_library, model="v1")
        page.locator("#cite").click()
        text = page.locator("#cite-text").input_value()
        bibtex = page.locator("#cite-bibtex").input_value()
    finally:
        context.close()
    assert f"Licence: {licence}" in text and "Scan by the Test Museum lab" in text
    assert f"licence: \\url{{{licence}}}" in bibtex
