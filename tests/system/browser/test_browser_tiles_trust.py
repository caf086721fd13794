"""Trust and quality shading on a streamed (tiled) face (issue 20 item 2 on issue 19's tiles):
each tile samples the face's whole trust.png / quality map through its rectangle of the face's
grid (tiles.js tileFaceUv), so the colours on screen are those of the map at the point shown,
on the coarse root tile and on the finest tiles, across tile boundaries.

The face is worker.simulate.large_face tiled by the worker's builder (as test_browser_tiles.py)
with a made-up trust.png and quality map: 64-pixel blocks whose class (trust) or value
(quality) changes from block to block, so a tile mapped to the wrong place or scale shows the
wrong block.
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from worker.simulate.large_face import write_large_face
from worker.tiles.build import build_tiles

server = sys.modules["hammurabi_browser_server"]  # loaded by conftest.py
VIEWPORT = {"width": 960, "height": 600}
BLOCK_PX = 64
W, H = 2048, 1536
# trust.js TRUST_CLASSES, sRGB
CLASS_SRGB = {
    1: (0.33, 0.63, 0.42),
    2: (0.89, 0.47, 0.13),
    3: (0.36, 0.55, 0.86),
    4: (0.84, 0.19, 0.56),
    5: (0.95, 0.84, 0.25),
}


def block_class(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The made-up source class of pixels (rows, cols): 1–5 cycling over 64-px blocks."""
    return (cols // BLOCK_PX + 2 * (rows // BLOCK_PX)) % 5 + 1


def to_linear(srgb: np.ndarray) -> np.ndarray:
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def classify(srgb_pixels: np.ndarray) -> np.ndarray:
    """Nearest trust class by chromaticity in linear RGB (the mode shades each class colour by
    the light, a factor on the linear colour)."""
    refs = to_linear(np.array([CLASS_SRGB[k] for k in sorted(CLASS_SRGB)]))
    refs /= np.linalg.norm(refs, axis=1, keepdims=True)
    lin = to_linear(srgb_pixels)
    lin /= np.maximum(np.linalg.norm(lin, axis=-1, keepdims=True), 1e-9)
    return np.argmax(lin @ refs.T, axis=-1) + 1


@pytest.fixture(scope="module")
def tiled_trust(library, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp("tiled-trust") / "model"
    report = write_large_face(model_dir, width_px=W, height_px=H, seed=11)
    build_tiles(model_dir)
    height = np.load(model_dir / "height.npy")
    on = np.isfinite(height)
    r, c = np.mgrid[0:H, 0:W]
    codes = block_class(r, c)
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., 0] = codes
    rgba[..., 3] = np.where(on, 255, 0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    assert ok
    (model_dir / "trust.png").write_bytes(png.tobytes())
    (model_dir / "trust.json").write_text(json.dumps({"class_fraction": {"1": 0.2}}))
    (model_dir / "quality").mkdir(exist_ok=True)
    q = ((c // BLOCK_PX + r // BLOCK_PX) % 2).astype(np.float32)
    np.save(model_dir / "quality" / "checker.npy", np.where(on, q, np.nan).astype(np.float32))
    np.save(model_dir / "uncertainty_um.npy", np.where(on, sigma_um(c, 0), np.nan))
    model_id = library.add_model("tiled-trust", "P999003", "reverse", model_dir)
    return SimpleNamespace(
        id=model_id,
        on=on,
        s_mm=report["pixel_size_um"] / 1000,
        height=np.load(model_dir / "height.npy"),
    )


@pytest.fixture(scope="module")
def trust_page(browser, library, tiled_trust):
    context = browser.new_context(viewport=VIEWPORT)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    tablet_id = library.tablets["P999003"]
    pg.goto(f"{library.url}/tablet.html?id={tablet_id}&tile_budget_mb=96#m={tiled_trust.id}")
    pg.wait_for_function("() => document.getElementById('viewer').dataset.loaded", timeout=60000)
    yield pg, errors
    context.close()


def look_at(page, x_mm: float, y_mm: float, zoom: float) -> None:
    page.evaluate(
        """([x, y, zoom]) => {
        const v = window.hammurabi.viewer;
        const s = v.getState();
        const d = Math.hypot(...s.camera.position.map((p, i) => p - s.camera.target[i]));
        v.setState({ camera: { projection: 'orthographic', position: [x, y, -d],
          target: [x, y, 0], up: [0, -1, 0], zoom } });
      }""",
        [x_mm, y_mm, zoom],
    )


def settle_tiles(page) -> dict:
    return server.settle_tiles(page)


def samples_on_screen(page, tools, t, rows, cols):
    """Screen colours (sRGB in [0, 1]) at image pixels (rows, cols) on the tablet and on the
    canvas, with the rows and cols kept."""
    box = page.locator("#viewer").bounding_box()
    px = tools.canvas_pixels(page)
    keep_r, keep_c, colours = [], [], []
    for r, c in zip(rows, cols, strict=True):
        # off the tablet or next to its rim (the tile mesh's rim is not the mask's)
        if not t.on[max(0, r - 3) : r + 4, max(0, c - 3) : c + 4].all():
            continue
        x, y = tools.screen_of(page, [c * t.s_mm, r * t.s_mm, 0.0])
        ix, iy = int(round(x - box["x"])), int(round(y - box["y"]))
        if 0 <= iy < px.shape[0] and 0 <= ix < px.shape[1]:
            keep_r.append(r)
            keep_c.append(c)
            colours.append(px[iy, ix])
    return np.array(keep_r), np.array(keep_c), np.array(colours)


def test_trust_and_quality_on_a_streamed_face_show_the_face_maps(trust_page, tiled_trust, tools):
    page, errors = trust_page
    t = tiled_trust
    # The modes are offered (not disabled as on a model without the maps).
    for sel in ("#mode", "#lens-mode"):
        for mode in ("trust", "quality"):
            assert not page.locator(f"{sel} option[value='{mode}']").is_disabled(), (sel, mode)
    page.select_option("#mode", "trust")
    page.wait_for_function("() => window.hammurabi.viewer.model.assets.trust")
    page.evaluate(
        """() => window.hammurabi.viewer.setState({ shading: { trustLayer: 'sources' },
          light: { azimuthDeg: 0, polarDeg: 20, intensity: 1, ambient: 0.15, gloss: 0 } })"""
    )
    assert page.locator("#trust-legend").is_visible()

    # Overview (the root tile, 4 pixels per texel) then zoomed across the corner of four
    # finest tiles (512-px tiles meet at pixel 1024, 1024): block centres, and at the zoom
    # pixels 3 px either side of each block edge.
    views = [
        (
            W / 2,
            H / 2,
            1,
            np.arange(BLOCK_PX // 2, H, BLOCK_PX),
            np.arange(BLOCK_PX // 2, W, BLOCK_PX),
        ),
        (1024, 1024, 10, None, None),
    ]
    for cx, cy, zoom, rr, cc in views:
        look_at(page, cx * t.s_mm, cy * t.s_mm, zoom)
        s = settle_tiles(page)
        if rr is None:
            edges = np.arange(1024 - 2 * BLOCK_PX, 1024 + 2 * BLOCK_PX + 1, BLOCK_PX)
            near = np.sort(np.concatenate([edges - 3, edges + 2, edges - BLOCK_PX // 2]))
            rr, cc = near, near
            assert s["minPixelStep"] == 1, s
        grid_r, grid_c = np.meshgrid(rr, cc, indexing="ij")
        r, c, colours = samples_on_screen(page, tools, t, grid_r.ravel(), grid_c.ravel())
        assert len(r) >= 30, (zoom, len(r))
        got = classify(colours)
        want = block_class(r, c)
        agree = (got == want).mean()
        assert agree > 0.95, (
            zoom,
            agree,
            list(zip(r[got != want], c[got != want], strict=True))[:10],
        )
        if zoom > 1:
            if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
                out = Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"]) / "viewer-tiles-trust.png"
                page.screenshot(path=str(out))

            # Quality at the same spot: the checker's 0 and 1 are the ramp's two ends (dark
            # violet, yellow), the same blocks, from the same per-tile mapping.
            page.evaluate("() => window.hammurabi.viewer.setShading({ mode: 'quality' })")
            page.wait_for_function("() => window.hammurabi.viewer.model.assets.quality?.length")
            settle_tiles(page)
            r, c, colours = samples_on_screen(page, tools, t, grid_r.ravel(), grid_c.ravel())
            yellow = colours[:, 1] > 0.5
            want_q = ((c // BLOCK_PX + r // BLOCK_PX) % 2).astype(bool)
            assert (yellow == want_q).mean() > 0.95, (yellow == want_q).mean()
            page.evaluate("() => window.hammurabi.viewer.setShading({ mode: 'trust' })")
    assert not errors, errors


def write_block_trust(path: Path, on: np.ndarray, shift: int) -> None:
    """A made-up trust.png: block_class shifted by ``shift`` classes (faces told apart)."""
    h, w = on.shape
    r, c = np.mgrid[0:h, 0:w]
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[..., 0] = (block_class(r, c) - 1 + shift) % 5 + 1
    rgba[..., 3] = np.where(on, 255, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    assert ok
    path.write_bytes(png.tobytes())


def quality_checker(rows: np.ndarray, cols: np.ndarray, face: int) -> np.ndarray:
    """The made-up quality map of face ``face`` (0 obverse, 1 reverse): 0/1 over 64-px blocks."""
    return ((cols // BLOCK_PX + rows // BLOCK_PX + face) % 2).astype(np.float32)


def sigma_um(cols: np.ndarray, face: int) -> np.ndarray:
    """The made-up σ_h (µm) of face ``face``: 5 µm + 0.1 µm per column, + 50 µm on the reverse."""
    return (5.0 + 0.1 * cols + 50.0 * face).astype(np.float32)


@pytest.fixture(scope="module")
def tablet_trust(library, tmp_path_factory):
    """A streamed whole tablet of two faces (as test_browser_tiles.py's), each with its own
    trust.png under faces/<label>/ on its own grid (the reverse 640 × 448, the obverse 768 × 512)."""
    from worker.tiles.tablet import build_tablet_tiles

    tmp = tmp_path_factory.mktemp("tablet_trust")
    faces, heights = {}, {}
    sizes = {"obverse": (768, 512), "reverse": (640, 448)}
    for k, (name, (w, h)) in enumerate(sizes.items()):
        d = tmp / name
        report = write_large_face(d, width_px=w, height_px=h, seed=21 + k)
        faces[name] = d
        heights[name] = np.load(d / "height.npy")
    s_mm = report["pixel_size_um"] / 1000
    w_mm = sizes["reverse"][0] * s_mm
    turn = np.diag([-1.0, 1.0, -1.0, 1.0])  # 180° about y: x → w − x, z → 12 mm − z
    turn[0, 3], turn[2, 3] = w_mm, 12.0
    model_dir = tmp / "tablet"
    model_dir.mkdir()
    (model_dir / "model.glb").write_bytes((faces["obverse"] / "model.glb").read_bytes())
    (model_dir / "report.json").write_text('{"scans": ["obverse", "reverse"]}')
    build_tablet_tiles(
        model_dir,
        {"faces/obverse": (faces["obverse"], np.eye(4)), "faces/reverse": (faces["reverse"], turn)},
    )
    for k, name in enumerate(sizes):
        on = np.isfinite(heights[name])
        write_block_trust(model_dir / "faces" / name / "trust.png", on, k)
        # Each face's own quality map (a checker, the reverse's the other way round) and σ_h
        # (a ramp along the columns, 50 µm more on the reverse), on its own grid.
        r, c = np.mgrid[0 : on.shape[0], 0 : on.shape[1]]
        (model_dir / "faces" / name / "quality").mkdir()
        q = np.where(on, quality_checker(r, c, k), np.nan).astype(np.float32)
        np.save(model_dir / "faces" / name / "quality" / "checker.npy", q)
        np.save(
            model_dir / "faces" / name / "uncertainty_um.npy", np.where(on, sigma_um(c, k), np.nan)
        )
    model_id = library.add_tablet_model("P999003", model_dir)
    return SimpleNamespace(id=model_id, heights=heights, s_mm=s_mm, turn=turn)


def _open_tablet_in_mode(page, library, t, mode: str, loaded: str) -> None:
    """Open the streamed whole tablet `t` and switch to `mode` once the model's `loaded`
    expression (on window.hammurabi.viewer.model) is true."""
    page.goto(f"{library.url}/tablet.html?id={library.tablets['P999003']}#m={t.id}")
    page.wait_for_function("() => document.getElementById('viewer').dataset.loaded", timeout=60000)
    assert not page.locator(f"#mode option[value='{mode}']").is_disabled()
    page.select_option("#mode", mode)
    page.wait_for_function(f"() => window.hammurabi.viewer.model.{loaded}")


def test_trust_on_a_streamed_whole_tablet_uses_each_faces_map(
    browser, library, tablet_trust, tools
):
    t = tablet_trust
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        _open_tablet_in_mode(page, library, t, "trust", "assets.trust")
        for k, (view, to_tablet) in enumerate((("obverse", np.eye(4)), ("reverse", t.turn))):
            page.evaluate("v => window.hammurabi.viewer.setView(v)", view)
            settle_tiles(page)
            hgt = t.heights[view]
            box = page.locator("#viewer").bounding_box()
            px = tools.canvas_pixels(page)
            rows = np.arange(BLOCK_PX // 2, hgt.shape[0], BLOCK_PX)
            cols = np.arange(BLOCK_PX // 2, hgt.shape[1], BLOCK_PX)
            got, want = [], []
            for r in rows:
                for c in cols:
                    if not np.isfinite(hgt[max(0, r - 3) : r + 4, max(0, c - 3) : c + 4]).all():
                        continue
                    p = to_tablet @ np.array([c * t.s_mm, r * t.s_mm, -hgt[r, c] / 1000, 1.0])
                    x, y = tools.screen_of(page, p[:3].tolist())
                    ix, iy = int(round(x - box["x"])), int(round(y - box["y"]))
                    if 0 <= iy < px.shape[0] and 0 <= ix < px.shape[1]:
                        got.append(classify(px[iy, ix][None])[0])
                        want.append((block_class(r, c) - 1 + k) % 5 + 1)
            assert len(got) >= 20, (view, len(got))
            agree = (np.array(got) == np.array(want)).mean()
            assert agree > 0.9, (view, agree)
            if view == "reverse" and os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
                out = (
                    Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"]) / "viewer-tiles-tablet-trust.png"
                )
                page.screenshot(path=str(out))
        assert not errors, errors
    finally:
        context.close()


def _tablet_point(t, face: str, r: int, c: int) -> list[float]:
    """Tablet-frame point (mm) of face pixel (r, c) on its heights."""
    to_tablet = np.eye(4) if face == "obverse" else t.turn
    h = t.heights[face][r, c]
    return (to_tablet @ np.array([c * t.s_mm, r * t.s_mm, -h / 1000, 1.0]))[:3].tolist()


def test_quality_pm_profile_and_section_on_a_streamed_whole_tablet(
    browser, library, tablet_trust, tools
):
    """The tools a whole tablet's model.glb has, on its streamed twin: each face's quality map
    on its tiles (one legend), ± of a distance from the face each end lies on, a profile and a
    section from each face's height.f32 read by Range (the fixture has no height.npy)."""
    t = tablet_trust
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    requests: list[str] = []
    page.on("request", lambda req: requests.append(req.url))
    try:
        login = {"email": server.STAFF_EMAIL, "password": server.STAFF_PASSWORD}
        assert page.request.post(f"{library.url}/api/v1/auth/login", data=login).ok
        _open_tablet_in_mode(page, library, t, "quality", "assets.quality?.length")
        for k, view in enumerate(("obverse", "reverse")):
            page.evaluate("v => window.hammurabi.viewer.setView(v)", view)
            settle_tiles(page)
            assert page.locator("#notice").is_hidden(), page.locator("#notice").inner_text()
            assert page.locator("#legend").is_visible()
            hgt = t.heights[view]
            box = page.locator("#viewer").bounding_box()
            px = tools.canvas_pixels(page)
            got, want = [], []
            for r in range(BLOCK_PX // 2, hgt.shape[0], BLOCK_PX):
                for c in range(BLOCK_PX // 2, hgt.shape[1], BLOCK_PX):
                    if not np.isfinite(hgt[max(0, r - 3) : r + 4, max(0, c - 3) : c + 4]).all():
                        continue
                    x, y = tools.screen_of(page, _tablet_point(t, view, r, c))
                    ix, iy = int(round(x - box["x"])), int(round(y - box["y"]))
                    if 0 <= iy < px.shape[0] and 0 <= ix < px.shape[1]:
                        got.append(px[iy, ix, 1] > 0.5)  # yellow (1) vs dark violet (0)
                        want.append(bool(quality_checker(np.array(r), np.array(c), k)))
            assert len(got) >= 20, (view, len(got))
            agree = (np.array(got) == np.array(want)).mean()
            assert agree > 0.9, (view, agree)
            if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
                out = Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"])
                page.locator(".stage").screenshot(
                    path=str(out / f"viewer-tiles-tablet-quality-{view}.png")
                )

        # ± of a distance on the reverse (in view): σ_h read on the reverse's own grid at each
        # end, along its viewing axis (trust.js distanceUncertaintyAxesMm).
        ends = [(150, 120), (230, 470)]
        a, b = (_tablet_point(t, "reverse", r, c) for r, c in ends)
        pm = page.evaluate("p => window.hammurabi.scholar.uncertainty.distance(p)", [a, b])
        e = np.subtract(b, a) / np.linalg.norm(np.subtract(b, a))
        cz = abs(e @ t.turn[:3, 2])
        s_um = t.s_mm * 1000
        want_pm = sum(
            cz * sigma_um(np.array(c), 1) + np.sqrt(1 - cz**2) * s_um / 2 for _, c in ends
        )
        assert pm == pytest.approx(want_pm / 1000, rel=1e-3), (pm, want_pm)

        # A profile on the reverse through the page's tool: its rows by Range, σ_h's band.
        page.locator("#mode").select_option("clay")
        settle_tiles(page)
        row = 200
        cols = [100, 500]
        page.locator("#viewer").focus()
        page.keyboard.press("h")
        for c in cols:
            page.mouse.click(*tools.screen_of(page, _tablet_point(t, "reverse", row, c)))
        page.wait_for_function("() => !document.getElementById('profile-panel').hidden")
        text = page.locator("#readout").inner_text()
        assert text.startswith("Profile on reverse: "), text
        n = int(re.search(r"(\d+) samples", text).group(1))
        assert abs(n - (cols[1] - cols[0])) <= 2, (n, text)
        median = float(re.search(r"heights ± ([\d.]+) µm", text).group(1))
        assert median == pytest.approx(float(sigma_um(np.array(np.mean(cols)), 1)), abs=2), text
        assert page.locator("#profile-chart path.band").count() == 1
        link = page.evaluate("() => window.hammurabi.ui.permalinkUrl()")
        page.keyboard.press("Escape")
        # The link restores the profile once the reverse's tiles (its frame) are in.
        other = context.new_page()
        other.goto(link)
        other.wait_for_function(
            "() => !document.getElementById('profile-panel').hidden", timeout=60000
        )
        # (the link's 7 significant digits may move the sample count by one)
        assert (
            other.locator("#readout").inner_text().split(" samples")[0][:-4]
            == text.split(" samples")[0][:-4]
        )
        assert other.locator("#profile-chart path.band").count() == 1
        other.close()

        # The best light from the reverse's tile under the click (its normals turned into the
        # tablet frame by the face's rotation).
        page.keyboard.press("w")
        page.mouse.click(*tools.screen_of(page, _tablet_point(t, "reverse", 220, 320)))
        strip = page.locator("#light-strip")
        strip.wait_for(state="visible")
        assert int(strip.get_attribute("data-normals")) > 50
        page.keyboard.press("Escape")

        # A section across the obverse along one row: the plane holds the view's axis, so it
        # cuts that row of the obverse and of the reverse (12 mm behind) at full resolution.
        page.evaluate("() => window.hammurabi.viewer.setView('obverse')")
        settle_tiles(page)
        row = 256
        page.locator("#viewer").focus()
        page.keyboard.press("x")
        for c in (60, 700):
            page.mouse.click(*tools.screen_of(page, _tablet_point(t, "obverse", row, c)))
        panel = page.locator("#section-panel")
        panel.wait_for(state="visible")
        assert panel.get_attribute("data-source") == "heights"
        xs, zs = [], []
        for face, to_tablet in (("obverse", np.eye(4)), ("reverse", t.turn)):
            h = t.heights[face][row]
            c = np.flatnonzero(np.isfinite(h))
            p = to_tablet @ np.stack(
                [c * t.s_mm, np.full(c.size, row * t.s_mm), -h[c] / 1000, np.ones(c.size)]
            )
            xs += [p[0].min(), p[0].max()]
            zs += [p[2].min(), p[2].max()]
        width = float(panel.get_attribute("data-width-mm"))
        depth = float(panel.get_attribute("data-depth-mm"))
        assert width == pytest.approx(np.ptp(xs), abs=2 * t.s_mm), (width, np.ptp(xs))
        assert depth == pytest.approx(np.ptp(zs), abs=0.02), (depth, np.ptp(zs))
        if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
            out = Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"])
            page.locator(".stage").screenshot(path=str(out / "viewer-tiles-tablet-section.png"))
        page.locator("#section-close").click()

        # A sign's region drawn on the reverse: in mm, and on the reverse's own image grid
        # (the picks' points taken onto the face's grid, not the tiles' own uv).
        page.evaluate("() => window.hammurabi.viewer.setView('reverse')")
        settle_tiles(page)
        square = [(150, 200), (150, 300), (250, 300), (250, 200)]  # (row, col) of the reverse
        page.locator("#annotation-new").click()  # the section tool stops: the clicks are ours
        assert page.locator("#section").get_attribute("aria-pressed") == "false"
        for k, (r, c) in enumerate(square):
            page.mouse.click(*tools.screen_of(page, _tablet_point(t, "reverse", r, c)))
            status = page.locator("#annotation-status")
            assert status.inner_text().startswith(f"{k + 1} point"), status.inner_text()
        page.locator("#annotation-reference").fill("r 1 1")
        page.locator("#annotation-save").click()
        page.wait_for_selector('#annotation-list li[data-ref="r 1 1"]')
        items = page.evaluate("() => window.hammurabi.annotations.state.items")
        (drawn,) = [a for a in items if a["modelId"] == t.id]
        assert drawn["imageFace"] == "reverse", drawn
        want_px = [(c, r) for r, c in square]
        assert np.allclose(drawn["polygonPx"], want_px, atol=0.5), drawn["polygonPx"]

        # Heights came from each face's height.f32, never a whole-grid .npy.
        assert any("faces/reverse/height.f32" in u for u in requests), requests[-20:]
        assert not any(u.endswith("height.npy") for u in requests)
        assert not errors, errors
    finally:
        context.close()


def test_pm_of_distances_and_profiles_on_a_streamed_face(trust_page, tiled_trust, tools):
    """σ_h (uncertainty_um.npy) gives a streamed face's distances their ± and its profiles
    their band, as on a face model, with the heights read from height.f32 by Range."""
    page, errors = trust_page
    t = tiled_trust
    page.evaluate("() => window.hammurabi.viewer.setShading({ mode: 'clay' })")
    look_at(page, W / 2 * t.s_mm, H / 2 * t.s_mm, 1)
    settle_tiles(page)

    def point(r, c):
        return [c * t.s_mm, r * t.s_mm, float(-t.height[r, c]) / 1000]

    ends = [(700, 500), (760, 1500)]
    a, b = (point(*e) for e in ends)
    pm = page.evaluate("p => window.hammurabi.scholar.uncertainty.distance(p)", [a, b])
    dxy = np.hypot(b[0] - a[0], b[1] - a[1])
    dz = abs(b[2] - a[2])
    d = np.hypot(dxy, dz)
    sig = [float(sigma_um(np.array(c), 0)) for _, c in ends]
    want = ((dz / d) * sum(sig) + (dxy / d) * t.s_mm * 1000) / 1000
    assert pm == pytest.approx(want, rel=1e-3), (pm, want)

    # Through the page's tools: a distance with its ±, a profile with its band.
    page.locator("#viewer").focus()
    page.keyboard.press("m")
    for e in ends:
        page.mouse.click(*tools.screen_of(page, point(*e)))
    page.wait_for_function(
        "() => document.getElementById('readout').dataset.uncertaintyMm !== undefined"
    )
    assert "±" in page.locator("#readout").inner_text()
    page.keyboard.press("Escape")
    row, cols = 768, (400, 1600)
    page.keyboard.press("h")
    for c in cols:
        page.mouse.click(*tools.screen_of(page, point(row, c)))
    page.wait_for_function("() => !document.getElementById('profile-panel').hidden")
    text = page.locator("#readout").inner_text()
    median = float(re.search(r"heights ± ([\d.]+) µm", text).group(1))
    assert median == pytest.approx(float(sigma_um(np.array(np.mean(cols)), 0)), abs=2), text
    assert page.locator("#profile-chart path.band").count() == 1
    page.keyboard.press("Escape")

    # Unsharp masking of the normals acts on the tiles (each tile's own normal map).
    before = tools.canvas_pixels(page)
    page.evaluate("() => window.hammurabi.viewer.setEnhance({ normalUnsharp: 4 })")
    settle_tiles(page)
    after = tools.canvas_pixels(page)
    page.evaluate("() => window.hammurabi.viewer.setEnhance({ normalUnsharp: 0 })")
    assert np.abs(after - before).mean() > 0.005, np.abs(after - before).mean()
    assert not errors, errors
