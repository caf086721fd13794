"""The reader's tools on the whole tablet and on every mode (issue 20's last gaps):

- trust on the whole (single-mesh) tablet: each face's own trust map (worker/register/run.py
  makes them from the face's quality maps), its legend, and the ± of distances and profiles
  read on the face a point lies on;
- sections cut from the full-resolution heights (each face's faces/<label>/height.npy on the
  whole tablet; height.npy on a face model), not the decimated mesh;
- the lens showing modes with maps of their own (curvature, accessibility, quality).

The whole tablet is the worker's own (`whole_tablet_model` plus the report's per-face pixel
size, as `register_model_dirs` writes it) from the simulator's ground truth of six faces at
their true poses, each with quality maps: fringe heights on the left half of its image grid
and none (normals only) on the right half."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

server = sys.modules["hammurabi_browser_server"]  # loaded by conftest.py
TABLET = "P999002"
SIZE = (160, 128)  # 214 µm pixels: the simulator makes six faces in a few seconds
SHOTS = os.environ.get("HAMMURABI_SAVE_SCREENSHOTS")
AGREE_RGB = (0.33, 0.63, 0.42)
NORMALS_RGB = (0.36, 0.55, 0.86)
BACKGROUND = np.array([0x1D, 0x1F, 0x24]) / 255


def _whole_tablet_dir(out: Path) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "worker" / "register"))
    try:
        from synthetic import write_gt_model_dirs
    finally:
        sys.path.pop(0)
    from worker.assets import derive_assets
    from worker.register.io import face_asset_dir, load_model_dir, write_output_dir
    from worker.register.run import whole_tablet_model

    paths, truths = write_gt_model_dirs(out / "faces", size=SIZE)
    for k, p in enumerate(paths):
        h = np.load(p / "height.npy")
        (p / "quality").mkdir(exist_ok=True)
        d = np.random.default_rng(k).normal(0.0, 2.0, h.shape).astype(np.float32)
        d[:, h.shape[1] // 2 :] = np.nan  # the right half: no fringe height
        np.save(p / "quality" / "fringe_disagreement_um.npy", d)
        np.save(p / "quality" / "lights_used.npy", np.full(h.shape, 4, np.int16))
        np.save(p / "quality" / "photometric_residual.npy", np.full(h.shape, 0.01, np.float32))
        derive_assets(p)  # curvature and accessibility, as the pipeline makes them per face
    loaded = [load_model_dir(p) for p in paths]
    files = whole_tablet_model(loaded, truths)
    faces = {
        c.label: {"assets": face_asset_dir(c.label), "pixel_size_um": raw["pixel_size_um"]}
        for c, raw in loaded
    }
    files["report.json"] = json.dumps({"scans": list(faces), "faces": faces}).encode()
    write_output_dir(out / "model", files)
    return {c.label: raw for c, raw in loaded}


@pytest.fixture(scope="module")
def whole(tmp_path_factory, server_module):
    tmp = tmp_path_factory.mktemp("scholar_whole")
    raw = _whole_tablet_dir(tmp / "whole")
    server_module.make_model_dir(tmp / "face", seed=5)
    lib = server_module.start_library(
        tmp / "lib", extra_models=[("face", TABLET, "obverse", tmp / "face")]
    )
    try:
        lib.models["whole"] = lib.add_tablet_model(TABLET, tmp / "whole" / "model")
        lib.raw = raw
        lib.face_height = np.load(tmp / "face" / "height.npy")
        yield lib
    finally:
        lib.stop()


def _open(page, lib, model: str, tools) -> None:
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}#m={lib.models[model]}")
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want",
        arg=str(lib.models[model]),
        timeout=60000,
    )
    tools.settle(page)


def _shot(page, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        page.locator(".stage").screenshot(path=str(Path(SHOTS) / name))


def _hue(rgb, ref) -> float:
    a = np.asarray(rgb) / max(float(np.sum(rgb)), 1e-6)
    b = np.asarray(ref) / sum(ref)
    return float(np.abs(a - b).sum(axis=-1).min()) if a.ndim == 1 else np.abs(a - b).sum(-1)


def _region(px, ref, tol=0.12):
    """(rows, cols) of canvas pixels whose hue is that of a trust class colour."""
    s = px.sum(axis=-1, keepdims=True)
    norm = px / np.maximum(s, 1e-6)
    ref = np.asarray(ref) / sum(ref)
    on = (np.abs(norm - ref).sum(-1) < tol) & (px.sum(-1) > 0.4)
    return np.argwhere(on)


def _centre_of(cells) -> tuple[int, int]:
    """A cell of the region near its median (rows, cols), inside it."""
    med = np.median(cells, axis=0)
    best = cells[np.argmin(np.abs(cells - med).sum(axis=1))]
    return int(best[0]), int(best[1])


def test_trust_and_its_pm_on_the_whole_tablet(page, whole, tools):
    _open(page, whole, "whole", tools)
    page.locator("#viewer").focus()
    page.keyboard.press("u")
    tools.settle(page)
    assert page.locator("#viewer").get_attribute("data-mode") == "trust"
    assert page.locator("#notice").is_hidden(), page.locator("#notice").inner_text()
    has = page.evaluate(
        "() => window.hammurabi.viewer.model.partMaterials.map((m) => m.uniforms.uHasTrust.value)"
    )
    assert len(has) == 6 and all(has), has
    assert page.locator("#mode option[value='trust']").is_enabled()
    # The legend: the whole tablet's shares; half of every face rests on the normals only.
    items = page.locator("#trust-legend li").all_inner_texts()
    share = float(re.search(r"\(([\d.]+) %\)", items[2]).group(1))
    assert 30 <= share <= 70, items
    px = tools.canvas_pixels(page)
    agree, normals = _region(px, AGREE_RGB), _region(px, NORMALS_RGB)
    assert len(agree) > 300 and len(normals) > 300, (len(agree), len(normals))
    _shot(page, "whole-tablet-trust.png")

    # A distance in each region, 30 px long: the one resting on the normals has the larger ±.
    box = page.locator("#viewer").bounding_box()
    pm = {}
    for label, cells in (("agree", agree), ("normals", normals)):
        r, c = _centre_of(cells)
        a = (box["x"] + c - 15, box["y"] + r)
        b = (box["x"] + c + 15, box["y"] + r)
        page.locator("#viewer").focus()
        page.keyboard.press("m")
        page.mouse.click(*a)
        page.mouse.click(*b)
        page.wait_for_function(
            "() => document.getElementById('readout').dataset.uncertaintyMm !== undefined"
        )
        assert "±" in page.locator("#readout").inner_text()
        pm[label] = float(page.locator("#readout").get_attribute("data-uncertainty-mm"))
        page.keyboard.press("Escape")
    assert 0 < pm["agree"] < pm["normals"], pm

    # A profile on one face: its heights and a band of σ_h, from that face's own grids.
    r, c = _centre_of(normals)
    page.locator("#viewer").focus()
    page.keyboard.press("h")
    page.mouse.click(box["x"] + c - 40, box["y"] + r)
    page.mouse.click(box["x"] + c + 20, box["y"] + r)
    page.wait_for_function("() => !document.getElementById('profile-panel').hidden")
    text = page.locator("#readout").inner_text()
    assert re.match(r"Profile on \S+: [\d.]+ mm, \d+ samples, heights ± ", text), text
    assert page.locator("#profile-chart path.band").count() == 1
    _shot(page, "whole-tablet-profile-band.png")
    page.keyboard.press("Escape")


def test_a_profile_across_two_faces_says_why_not(page, whole, tools):
    _open(page, whole, "whole", tools)
    page.evaluate("() => window.hammurabi.viewer.setView('top')")
    tools.settle(page)
    # From the obverse over the top edge to the reverse, across the view's middle column.
    box = page.locator("#viewer").bounding_box()
    hits = page.evaluate(
        """([x, y0, y1]) => {
          const v = window.hammurabi.viewer;
          const out = [];
          for (let y = y0; y <= y1; y += 4) { const h = v.pick(x, y); out.push(h ? h.part : null); }
          return out;
        }""",
        [box["x"] + box["width"] / 2, box["y"] + 40, box["y"] + box["height"] - 40],
    )
    parts = [p for p in hits if p]
    assert len(set(parts)) >= 2, hits
    first = next(i for i, p in enumerate(hits) if p)
    last = max(i for i, p in enumerate(hits) if p and p != hits[first])
    page.locator("#viewer").focus()
    page.keyboard.press("h")
    x = box["x"] + box["width"] / 2
    page.mouse.click(x, box["y"] + 40 + 4 * first + 2)
    page.mouse.click(x, box["y"] + 40 + 4 * last - 2)
    page.wait_for_function(
        "() => document.getElementById('readout').textContent.includes('two faces')"
    )
    assert page.locator("#profile-panel").is_hidden()


def test_a_section_of_the_whole_tablet_is_cut_from_each_faces_heights(page, whole, tools):
    _open(page, whole, "whole", tools)
    page.locator("#mode").select_option("clay")
    tools.settle(page)
    model_box = page.evaluate("() => window.hammurabi.viewer.model.box")
    panel = server.cut_section(page, 60)
    assert panel.get_attribute("data-source") == "heights"
    assert "full-resolution heights" in page.locator("#section-readout").inner_text()
    width = float(panel.get_attribute("data-width-mm"))
    depth = float(panel.get_attribute("data-depth-mm"))
    extent = np.subtract(model_box["max"], model_box["min"])
    # Across the tablet through its middle: nearly its full width and its full thickness.
    assert 0.8 * extent[0] < width <= extent[0] + 0.05, (width, extent)
    assert 0.85 * extent[2] < depth <= extent[2] + 0.05, (depth, extent)
    _shot(page, "whole-tablet-section.png")
    with page.expect_download() as dl:
        page.locator("#section-svg").click()
    svg = Path(dl.value.path()).read_text()
    w_mm = float(re.search(r'width="([\d.]+)mm"', svg).group(1))
    assert w_mm == pytest.approx(width * 1.16, rel=0.02)  # true scale, 8 % margin each side
    assert "cut from the full-resolution heights" in svg
    page.locator("#section-close").click()


def test_a_face_models_section_is_its_full_resolution_heights(page, whole, tools):
    _open(page, whole, "face", tools)
    row = 160  # y = 16 mm on the fixture's 100 µm grid
    page.locator("#viewer").focus()
    page.keyboard.press("x")
    for x in (5.0, 43.0):
        page.mouse.click(*tools.screen_of(page, (x, row / 10, -1.0)))
    panel = page.locator("#section-panel")
    panel.wait_for(state="visible")
    assert panel.get_attribute("data-source") == "heights"
    # The plane holds the obverse view's axis: the outline is the row's heights, rim to rim.
    h = whole.face_height[row]
    assert float(panel.get_attribute("data-width-mm")) == pytest.approx((h.size - 1) / 10, abs=0.11)
    depth = float(panel.get_attribute("data-depth-mm"))
    assert depth == pytest.approx(np.ptp(h) / 1000, rel=0.02), (depth, np.ptp(h))
    page.locator("#section-close").click()


@pytest.mark.parametrize("mode", ["curvature", "accessibility", "quality"])
def test_the_lens_shows_modes_with_maps_of_their_own(page, whole, tools, mode):
    _open(page, whole, "face", tools)
    page.locator("#mode").select_option(mode)
    tools.settle(page)
    full = tools.canvas_pixels(page)
    page.locator("#mode").select_option("clay")
    page.locator("#lens-mode").select_option(mode)
    page.locator("#lens-on").check()
    tools.settle(page)
    assert page.evaluate("() => window.hammurabi.viewer.enhance.lens.mode") == mode
    assert page.locator("#notice").is_hidden(), page.locator("#notice").inner_text()
    lens = page.evaluate("() => window.hammurabi.viewer.enhance.lens")
    px = tools.canvas_pixels(page)
    yy, xx = np.mgrid[: px.shape[0], : px.shape[1]]
    dist = np.hypot(xx - lens["x"], yy - lens["y"])
    inside = (dist < 0.8 * lens["radius"]) & (np.abs(full - BACKGROUND).sum(-1) > 0.05)
    outside = dist > 1.2 * lens["radius"]
    assert inside.sum() > 200
    # Inside the circle the mode as it is drawn on its own; outside, clay as before.
    assert np.abs(px[inside] - full[inside]).mean() < 0.02, mode
    page.locator("#lens-on").uncheck()
    tools.settle(page)
    clay = tools.canvas_pixels(page)
    assert np.abs(px[outside] - clay[outside]).max() < 0.02
    assert np.abs(px[inside] - clay[inside]).mean() > 0.05, mode
    if mode == "curvature":
        page.locator("#lens-on").check()
        tools.settle(page)
        _shot(page, "viewer-lens-curvature.png")


def test_quality_and_best_light_on_the_whole_tablet(page, whole, tools):
    """Each face's own quality maps (faces/<label>/quality/*.npy) drawn on it against one
    legend; the best light reads the normals of the face clicked."""
    _open(page, whole, "whole", tools)
    assert page.locator("#mode option[value='quality']").is_enabled()
    page.locator("#mode").select_option("quality")
    page.wait_for_function("() => window.hammurabi.viewer.model.assets.quality?.length")
    page.locator("#quality-map").select_option("quality/fringe_disagreement_um.npy")
    tools.settle(page)
    assert page.locator("#notice").is_hidden(), page.locator("#notice").inner_text()
    assert page.locator("#legend").is_visible()
    assert "fringe_disagreement_um" in page.locator("#legend").inner_text()
    has = page.evaluate(
        "() => window.hammurabi.viewer.model.partMaterials.map((m) => m.uniforms.uHasQuality.value)"
    )
    assert len(has) == 6 and all(has), has
    # The left half of each face has a fringe disagreement (the ramp), the right half none
    # (NaN: flat grey 0.2 linear, 0.48 in sRGB).
    px = tools.canvas_pixels(page)
    model = np.abs(px - BACKGROUND).sum(-1) > 0.05
    grey = model & (np.abs(px - 0.485).max(-1) < 0.02)
    ramp = model & (px.max(-1) - px.min(-1) > 0.15)
    assert grey.sum() > 300 and ramp.sum() > 300, (grey.sum(), ramp.sum())
    _shot(page, "whole-tablet-quality.png")

    page.locator("#mode").select_option("clay")
    box = page.locator("#viewer").bounding_box()
    page.locator("#viewer").focus()
    page.keyboard.press("w")
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    strip = page.locator("#light-strip")
    strip.wait_for(state="visible")
    assert int(strip.get_attribute("data-normals")) > 50
    assert page.locator("#light-strip-cells canvas").count() == 8
    page.keyboard.press("Escape")
