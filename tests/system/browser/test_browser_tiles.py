"""A streamed (tiled) model in the viewer (issue 19): the 3D Tiles tileset is loaded instead of
the single mesh, refined where the camera looks, relit from each tile's full-resolution
normals, within the GPU memory budget, fetching less than the whole data; the profile reads
heights by HTTP Range.

The model is a procedural face (worker.simulate.large_face, 2048 × 1536 px at 26.8 µm) tiled
by the worker's own builder (worker.tiles: three levels of 512-texel tiles); the camera zooms
into its most detailed spot (a wedge), whose facets are finer than the coarse levels' texels.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import uniform_filter

from worker.simulate.large_face import write_large_face
from worker.tiles.build import build_tiles

server = sys.modules["hammurabi_browser_server"]  # loaded by conftest.py
VIEWPORT = {"width": 960, "height": 600}

BUDGET_MB = 64  # about two thirds of all the tiles on the GPU (17 tiles of ~5.6 MB)
ERROR_PX = 1  # a texel of the maps at most one screen pixel
SCREENSHOTS = Path(__file__).resolve().parents[3] / "docs" / "screenshots"


@pytest.fixture(scope="module")
def tiled(library, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp("tiled") / "model"
    report = write_large_face(model_dir, width_px=2048, height_px=1536, seed=7)
    build_tiles(model_dir)
    model_id = library.add_model("tiled", "P999003", "obverse", model_dir)
    full_bytes = sum(p.stat().st_size for p in (model_dir / "tiles" / "3d").rglob("*.glb"))
    normals = np.asarray(Image.open(model_dir / "normals.png").convert("RGB"))
    # the most detailed spot: where the normals vary most over ~1 mm (a wedge)
    n = normals.astype(np.float64) / 255 * 2 - 1
    detail = uniform_filter(np.hypot(n[..., 0], n[..., 1]), 40)
    r, c = np.unravel_index(np.argmax(detail), detail.shape)
    s_mm = report["pixel_size_um"] / 1000
    return SimpleNamespace(
        dir=model_dir,
        id=model_id,
        full_bytes=full_bytes,
        normals=normals,
        pixel_size_um=report["pixel_size_um"],
        wedge_mm=(c * s_mm, r * s_mm),
        size_mm=(2048 * s_mm, 1536 * s_mm),
    )


@pytest.fixture(scope="module")
def tiled_page(browser, library, tiled):
    context = browser.new_context(viewport=VIEWPORT)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    pg.on("console", lambda m: errors.append(m.text) if "Content Security" in m.text else None)
    tablet_id = library.tablets["P999003"]
    pg.goto(
        f"{library.url}/tablet.html?id={tablet_id}&tile_budget_mb={BUDGET_MB}"
        f"&tile_error_px={ERROR_PX}#m={tiled.id}"
    )
    pg.wait_for_function("() => document.getElementById('viewer').dataset.loaded", timeout=60000)
    yield pg, errors
    context.close()


def streaming(page) -> dict:
    return page.evaluate("() => window.hammurabi.viewer.streaming()")


def wait_streamed(page) -> dict:
    """No tile queued, downloading or parsing after a drawn frame, twice in a row."""
    return server.settle_tiles(page)


def tile_bytes_fetched(page) -> int:
    """Bytes of the distinct tile contents the page downloaded (Resource Timing, same origin):
    a tile evicted and asked for again comes from the browser's HTTP cache."""
    return page.evaluate(
        """() => { const seen = new Map();
          for (const e of performance.getEntriesByType('resource')) {
            if (e.name.includes('/assets/tiles/3d/') && e.name.endsWith('.glb')) {
              seen.set(e.name, Math.max(seen.get(e.name) ?? 0, e.encodedBodySize));
            }
          }
          return [...seen.values()].reduce((n, b) => n + b, 0); }"""
    )


def zoom_to(page, x_mm: float, y_mm: float, zoom: float) -> None:
    """Look straight at (x, y) on the obverse with an orthographic zoom (viewer.setState)."""
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


def relit_line(normals_png: np.ndarray, cols: np.ndarray, row: float, light: np.ndarray):
    """max(0, n·l) along image row ``row`` at fractional columns ``cols``, the normals
    bilinearly interpolated from the full-resolution map (RGB = (n+1)/2)."""
    n = normals_png.astype(np.float64) / 255 * 2 - 1
    r0 = int(np.floor(row))
    fr = row - r0
    c0 = np.floor(cols).astype(int)
    fc = (cols - c0)[:, None]
    rowv = n[r0] * (1 - fr) + n[r0 + 1] * fr
    v = rowv[c0] * (1 - fc) + rowv[c0 + 1] * fc
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return np.maximum(0, v @ light)


def tile_under_centre(page) -> dict | None:
    """describeTile (tiles.js) of the tile drawn at the centre of the canvas."""
    box = page.locator("#viewer").bounding_box()
    return page.evaluate(
        """([x, y]) => { const v = window.hammurabi.viewer; const hit = v.pick(x, y);
          return hit && v.model.tiles.describeTile(hit.object); }""",
        [box["x"] + box["width"] / 2, box["y"] + box["height"] / 2],
    )


def test_a_tiled_model_streams_relights_and_stays_in_budget(tiled_page, tiled, tools):
    page, errors = tiled_page
    wx, wy = tiled.wedge_mm

    # The overview: the coarse root on screen first (a texel of level 0 is 4 pixels, under
    # one screen pixel at this size).
    s = wait_streamed(page)
    assert s["visibleTiles"] >= 1 and s["maxLevel"] == 0 and s["minPixelStep"] == 4, s
    overview_bytes = tile_bytes_fetched(page)
    assert 0 < overview_bytes < tiled.full_bytes / 4, (overview_bytes, tiled.full_bytes)

    # Clay, raking light from the right (φ = 90°, θ = 75°), zoomed 8× onto the wedge.
    page.evaluate(
        """() => window.hammurabi.viewer.setState({ shading: { mode: 'clay' },
          light: { azimuthDeg: 90, polarDeg: 75, intensity: 1, ambient: 0.15, gloss: 0 } })"""
    )
    zoom_to(page, wx, wy, 8)
    s = wait_streamed(page)
    assert s["bytesUsed"] <= s["budgetBytes"] == BUDGET_MB * 1024 * 1024, s
    under = tile_under_centre(page)
    assert under is not None and under["pixel_step"] == 1 and under["sufficient"], under

    # The rendered detail across the wedge matches the full-resolution normals relit on the
    # CPU: correlation along a line of screen pixels, better than with a 4-pixel sampling
    # (what the root's texels hold).
    box = page.locator("#viewer").bounding_box()
    px = tools.canvas_pixels(page).mean(axis=-1)
    xs_mm = np.linspace(wx - 1.5, wx + 1.5, 241)
    screen = np.array([tools.screen_of(page, [x, wy, 0.0]) for x in xs_mm])
    rendered = px[
        np.round(screen[:, 1] - box["y"]).astype(int), np.round(screen[:, 0] - box["x"]).astype(int)
    ]
    theta, phi = np.radians(75), np.radians(90)
    light = np.array([np.sin(theta) * np.sin(phi), np.sin(theta) * np.cos(phi), -np.cos(theta)])
    cols = xs_mm * 1000 / tiled.pixel_size_um
    row = wy * 1000 / tiled.pixel_size_um
    full = relit_line(tiled.normals, cols, row, light)
    coarse = relit_line(tiled.normals, np.round(cols / 4) * 4, row, light)
    r_full = np.corrcoef(rendered, full)[0, 1]
    r_coarse = np.corrcoef(rendered, coarse)[0, 1]
    assert r_full > 0.95, (r_full, r_coarse)
    assert r_full > r_coarse + 0.01, (r_full, r_coarse)

    # Every shading mode draws the tiles from their own maps: each view has structure
    # (the wedges) and differs from the others; the per-scan quality maps are not streamed.
    shots, gpu = {}, {}
    for mode in ("natural", "curvature", "accessibility", "relief", "depth", "normals"):
        page.evaluate("m => window.hammurabi.viewer.setShading({ mode: m })", mode)
        shots[mode] = tools.render_pixels(page)
        gpu[mode] = streaming(page)["bytesUsed"]
        assert shots[mode].std() > 0.02, mode
    # the curvature and accessibility maps are on the GPU (and counted) only in their modes
    assert gpu["curvature"] > gpu["natural"] and gpu["accessibility"] > gpu["natural"], gpu
    assert gpu["relief"] == gpu["natural"], gpu
    # ... and while the lens draws them over another mode (counted as the lens' maps too)
    page.evaluate(
        """() => { const v = window.hammurabi.viewer; v.setShading({ mode: 'natural' });
          v.setEnhance({ lens: { mode: 'curvature', x: 200, y: 200, radius: 80 } }); }"""
    )
    tools.render_pixels(page)
    lens_bytes = streaming(page)["bytesUsed"]
    page.evaluate("() => window.hammurabi.viewer.setEnhance({ lens: null })")
    tools.render_pixels(page)
    assert lens_bytes > streaming(page)["bytesUsed"] == gpu["natural"], (lens_bytes, gpu)
    names = list(shots)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert np.abs(shots[a] - shots[b]).mean() > 0.01, (a, b)
    page.evaluate("() => window.hammurabi.viewer.setShading({ mode: 'quality' })")
    assert "quality" in page.locator("#notice").inner_text()
    page.evaluate("() => window.hammurabi.viewer.setShading({ mode: 'clay' })")

    if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
        page.locator("#viewer").screenshot(
            path=str(Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"]) / "viewer-tiles-zoom.png")
        )

    # Two more zooms elsewhere: full detail there too, the cache within the budget, and less
    # than the whole tileset downloaded.
    w, h = tiled.size_mm
    for x, y in ((0.25 * w, 0.3 * h), (0.7 * w, 0.75 * h)):
        zoom_to(page, x, y, 8)
        s = wait_streamed(page)
        assert s["bytesUsed"] <= s["budgetBytes"], s
        under = tile_under_centre(page)
        assert under is not None and under["pixel_step"] == 1, under
    fetched = tile_bytes_fetched(page)
    assert fetched < tiled.full_bytes, (fetched, tiled.full_bytes)
    assert not errors, errors


def test_profile_reads_only_the_rows_it_touches(tiled_page, tiled, tools):
    """A height profile on a streamed model, drawn through the page's tool: heights from
    tiles/height.f32 by HTTP Range (never height.npy), the same values as height.npy, and far
    fewer bytes than the file."""
    page, errors = tiled_page
    page.evaluate("() => window.hammurabi.viewer.resetView()")
    wait_streamed(page)
    wx, wy = tiled.wedge_mm
    a, b = [wx - 4, wy, 0.0], [wx + 4, wy, 0.0]
    page.locator("#viewer").focus()
    page.keyboard.press("h")
    for p in (a, b):
        x, yy = tools.screen_of(page, p)
        page.mouse.click(x, yy)
    page.wait_for_selector("#profile-panel:not([hidden]) svg path.line")
    assert page.locator("#readout").inner_text().startswith("Profile:")
    names = page.evaluate(
        "() => performance.getEntriesByType('resource').map(e => e.name.split('/assets/')[1])"
    )
    assert "tiles/height.f32" in names and "height.npy" not in names, names
    out = page.evaluate(
        """async ([a, b]) => {
        const h = window.hammurabi.viewer.model.tiles.heights;
        const part = await h.reader.gridForSegment(a, b, h.pixelSizeUm);
        return { stats: h.reader.stats, start: part.start, cols: part.grid.cols,
                 values: Array.from(part.grid.heightUm.slice(0, 2 * part.grid.cols)) };
      }""",
        [a[:2], b[:2]],
    )
    height = np.load(tiled.dir / "height.npy")
    assert 0 < out["stats"]["bytesFetched"] < height.nbytes / 4, (out["stats"], height.nbytes)
    r0 = round((a[1] - out["start"][1]) * 1000 / tiled.pixel_size_um)
    got = np.asarray(out["values"], dtype=np.float64).reshape(2, out["cols"])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(height[r0 : r0 + 2]))
    np.testing.assert_allclose(got, height[r0 : r0 + 2], rtol=1e-6, equal_nan=True)
    page.keyboard.press("Escape")
    assert not errors, errors


def test_section_reads_rows_and_best_light_reads_the_tile(tiled_page, tiled, tools):
    """A streamed face is cut from its full-resolution heights, the rows between the two ends
    read by HTTP Range as a profile reads them (scholar.js); the best light reads the region
    from the normal map of the tile clicked (coarse or finest: the same light). A face without
    trust.png has its trust mode disabled, with the reason."""
    page, errors = tiled_page
    page.evaluate("() => window.hammurabi.viewer.resetView()")
    wait_streamed(page)
    wx, wy = tiled.wedge_mm
    page.locator("#section").click()
    assert page.locator("#section").get_attribute("aria-pressed") == "true"
    for p in ([wx - 3, wy, 0.0], [wx + 3, wy, 0.0]):
        page.mouse.click(*tools.screen_of(page, p))
    panel = page.locator("#section-panel")
    panel.wait_for(state="visible")
    assert panel.get_attribute("data-source") == "heights"
    # The plane holds the view's axis: the row's heights from rim to rim of the tablet.
    width = float(panel.get_attribute("data-width-mm"))
    s_mm = tiled.pixel_size_um / 1000
    row = np.load(tiled.dir / "height.npy", mmap_mode="r")[int(wy / s_mm)]
    cols = np.flatnonzero(np.isfinite(row))
    assert width == pytest.approx((cols[-1] - cols[0]) * s_mm, abs=3 * s_mm), width
    page.locator("#section-close").click()
    page.locator("#section").click()  # off
    trust = page.locator("#mode option[value='trust']")
    assert trust.is_disabled() and "streamed" in trust.get_attribute("title")
    assert page.locator("#lens-mode option[value='trust']").is_disabled()
    page.locator("#viewer").focus()
    page.keyboard.press("u")
    assert page.locator("#viewer").get_attribute("data-mode") != "trust"
    assert "streamed" in page.locator("#readout").inner_text()
    best = {}
    for zoom in (1, 8):
        zoom_to(page, wx, wy, zoom)
        wait_streamed(page)
        step = tile_under_centre(page)["pixel_step"]
        page.locator("#viewer").focus()
        page.keyboard.press("w")
        assert page.locator("#best-light").get_attribute("aria-pressed") == "true"
        page.mouse.click(*tools.screen_of(page, [wx, wy, 0.0]))
        strip = page.locator("#light-strip")
        strip.wait_for(state="visible")
        assert page.locator("#light-strip-cells canvas").count() == 8
        # A 3 mm circle of the tile's normals: π (3 mm / texel)² texels (read at most 192 on a
        # side, scholar.js MAX_CROP_PX; less where the circle leaves the tile).
        n = int(strip.get_attribute("data-normals"))
        r_tex = min(3000 / (tiled.pixel_size_um * step), 96)
        assert 0.25 * np.pi * r_tex**2 < n <= 1.1 * np.pi * r_tex**2 + 50, (zoom, step, n)
        best[zoom] = float(strip.get_attribute("data-azimuth"))
        light = page.evaluate("() => window.hammurabi.viewer.light")
        assert abs(light["azimuthDeg"] - best[zoom]) < 0.01 and not light["follow"]
        page.keyboard.press("Escape")  # the tool off, the strip closed
        assert page.locator("#light-strip").is_hidden()
    # Lighting across the same wedges (either side of them: modulo 180°).
    diff = abs((best[1] - best[8] + 90) % 180 - 90)
    assert diff <= 20, best
    assert not errors, errors


@pytest.fixture(scope="module")
def tiled_tablet(library, tmp_path_factory):
    """A whole tablet of two procedural faces (worker.tiles.tablet): the obverse as scanned,
    the reverse turned 180° about the vertical axis and 12 mm behind it."""
    from worker.tiles.tablet import build_tablet_tiles

    tmp = tmp_path_factory.mktemp("tiled_tablet")
    faces = {}
    for k, name in enumerate(("obverse", "reverse")):
        d = tmp / name
        report = write_large_face(d, width_px=768, height_px=512, seed=11 + k)
        faces[name] = d
    w_mm = 768 * report["pixel_size_um"] / 1000
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
    model_id = library.add_tablet_model("P999003", model_dir)
    return SimpleNamespace(id=model_id, w_mm=w_mm)


def test_a_whole_tablet_streams_face_by_face(browser, library, tiled_tablet):
    """Both faces' tilesets (external tilesets under the tablet's root) stream, each in its
    place in the tablet frame: the obverse seen from the front, the reverse from behind."""
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        tablet_id = library.tablets["P999003"]
        # an unusable setting in the link is ignored (the default budget stands) and named
        page.goto(f"{library.url}/tablet.html?id={tablet_id}&tile_budget_mb=0#m={tiled_tablet.id}")
        page.wait_for_function(
            "() => document.getElementById('viewer').dataset.loaded", timeout=60000
        )
        assert "tile_budget_mb=0" in page.locator("#notice").inner_text()
        assert wait_streamed(page)["budgetBytes"] == 256 * 1024 * 1024
        assert "reverse" in page.evaluate("() => window.hammurabi.viewer.views")
        hits = {}
        for view in ("obverse", "reverse"):
            page.evaluate("v => window.hammurabi.viewer.setView(v)", view)
            s = wait_streamed(page)
            assert s["visibleTiles"] >= 1, s
            hits[view] = (
                tile_under_centre(page),
                page.evaluate(
                    """() => { const c = document.getElementById('viewer').getBoundingClientRect();
                  const hit = window.hammurabi.viewer.pick(c.x + c.width / 2, c.y + c.height / 2);
                  return hit && hit.point; }"""
                ),
            )
        # the obverse's surface faces −z (heights toward the camera: z ≤ 0); the reverse's
        # lies beyond the 12 mm turn
        assert hits["obverse"][1] is not None and hits["obverse"][1][2] < 1.0, hits
        assert hits["reverse"][1] is not None and hits["reverse"][1][2] > 8.0, hits
        assert all(h[0] is not None for h in hits.values()), hits
        assert not errors, errors
    finally:
        context.close()


def test_tiles_under_the_cursor_load_first(browser, library, tiled, tools):
    """After a wheel zoom the finest tiles load in the order of their parent's distance from
    the cursor (tileFocus.js): the family of the tile under the cursor first. One download and
    one parse at a time, so the order of arrival is the queues' order."""
    context = browser.new_context(viewport=VIEWPORT)
    page = context.new_page()
    try:
        tablet_id = library.tablets["P999003"]
        page.goto(f"{library.url}/tablet.html?id={tablet_id}#m={tiled.id}")
        page.wait_for_function(
            "() => document.getElementById('viewer').dataset.loaded", timeout=60000
        )
        wait_streamed(page)
        page.evaluate(
            """() => { const t = window.hammurabi.viewer.model.tiles.tiles;
              t.downloadQueue.maxJobsPerOrigin = 1; t.parseQueue.maxJobs = 1;
              window.__loads = [];
              t.addEventListener('load-model', ({ tile }) => window.__loads.push({
                step: tile.extras?.dh_tile?.pixel_step,
                parent: tile.parent?.extras?.dh_tile?.px_rect ?? null })); }"""
        )
        # a point off the centre, near where four level-1 tiles (1024 px squares) meet, so
        # that the zoomed view needs the finest tiles of several families
        s_mm = tiled.pixel_size_um / 1000
        x, y = tools.screen_of(page, [900 * s_mm, 900 * s_mm, 0.0])
        hit = page.evaluate("([x, y]) => window.hammurabi.viewer.pick(x, y)?.point", [x, y])
        assert hit is not None
        page.mouse.move(x, y)
        page.mouse.wheel(0, -100 * np.log(4) / -np.log(0.95))  # x4 (OrbitControls: 0.95 / 100)
        wait_streamed(page)
        loads = page.evaluate("() => window.__loads")
        c = np.array(hit[:2]) * 1000 / tiled.pixel_size_um  # the cursor on the image grid, px
        dist = [
            float(np.hypot(max(r[0] - c[0], 0, c[0] - r[2]), max(r[1] - c[1], 0, c[1] - r[3])))
            for r in (t["parent"] for t in loads if t["step"] == 1 and t["parent"])
        ]
        assert len(set(dist)) >= 2, (loads, c)  # families at different distances loaded
        assert dist == sorted(dist), (dist, c)
        assert dist[0] == 0, dist  # the family under the cursor first
    finally:
        context.close()
