"""A streamed (tiled) model in the viewer (issue 19): the 3D Tiles tileset is loaded instead of
the single mesh, refined where the camera looks, relit from each tile's full-resolution
normals, within the GPU memory budget, fetching less than the whole data; the profile reads
heights by HTTP Range.

The model is the synthetic face (synthetic_model.py: analytic groove known to the test) with
tiles/ written by the tile builder; the camera zooms into the groove, whose walls exist only
in the normal maps (the coarsest level has one texel every 8 pixels)."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

server = sys.modules["hammurabi_browser_server"]  # loaded by conftest.py
tiles_fixture = server.load_sibling("tiles_fixture")
VIEWPORT = {"width": 960, "height": 600}

BUDGET_MB = 12  # three quarters of all the tiles on the GPU: eviction must happen
ERROR_PX = 4  # coarse at the overview (the root only), leaves once zoomed
SCREENSHOTS = Path(__file__).resolve().parents[3] / "docs" / "screenshots"


@pytest.fixture(scope="module")
def tiled(library, tmp_path_factory):
    model_dir = tmp_path_factory.mktemp("tiled") / "model"
    facts = server.make_model_dir(model_dir, seed=5)
    tiles_fixture.write_tiles(model_dir, pixel_size_um=facts.pixel_size_um, levels=4)
    model_id = library.add_model("tiled", "P999003", "obverse", model_dir)
    full_bytes = sum(p.stat().st_size for p in (model_dir / "tiles" / "3d").rglob("*.glb"))
    return SimpleNamespace(dir=model_dir, facts=facts, id=model_id, full_bytes=full_bytes)


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
    """Wait until, after a drawn frame (which runs the renderer's update), no tile is queued,
    downloading or parsing, twice in a row."""
    page.evaluate(
        """async () => {
        const v = window.hammurabi.viewer;
        const frame = () => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)));
        const deadline = performance.now() + 60000;
        let calm = 0;
        while (calm < 2) {
          v.invalidate();
          await frame();
          calm = v.streaming().idle ? calm + 1 : 0;
          if (performance.now() > deadline) throw new Error('tiles still loading after 60 s');
          if (!calm) await new Promise(r => setTimeout(r, 50));
        }
      }"""
    )
    return streaming(page)


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


def test_a_tiled_model_streams_relights_and_stays_in_budget(tiled_page, tiled, tools):
    page, errors = tiled_page
    f = tiled.facts

    # The overview: the coarse root on screen first.
    s = wait_streamed(page)
    assert s["visibleTiles"] >= 1 and s["maxLevel"] <= 1 and s["minPixelStep"] >= 4, s
    overview_bytes = tile_bytes_fetched(page)
    assert 0 < overview_bytes < tiled.full_bytes / 4, (overview_bytes, tiled.full_bytes)

    # Clay, raking light from the right (φ = 90°, θ = 75°): the groove's left wall is lit.
    page.evaluate(
        """() => window.hammurabi.viewer.setState({ shading: { mode: 'clay' },
          light: { azimuthDeg: 90, polarDeg: 75, intensity: 1, ambient: 0.15, gloss: 0 } })"""
    )
    y_mid = 10.0  # on the groove, in the upper half of the face
    zoom_to(page, f.groove_x_mm, y_mid, 8)
    s = wait_streamed(page)
    assert s["minPixelStep"] == 1, s  # full resolution where the camera looks
    assert s["bytesUsed"] <= s["budgetBytes"] == BUDGET_MB * 1024 * 1024, s
    # the tile under the centre of the view is a leaf (pixel step 1)
    box = page.locator("#viewer").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    under = page.evaluate(
        """([x, y]) => { const v = window.hammurabi.viewer;
          const hit = v.pick(x, y); return hit && hit.point; }""",
        [cx, cy],
    )
    assert under is not None and abs(under[0] - f.groove_x_mm) < 0.05, under

    # The rendered detail across the groove matches the full-resolution normals relit on the
    # CPU: correlation along a line of screen pixels, better than with the coarsest level's.
    px = tools.canvas_pixels(page).mean(axis=-1)
    xs_mm = np.linspace(f.groove_x_mm - 1.5, f.groove_x_mm + 1.5, 241)
    screen = np.array([tools.screen_of(page, [x, y_mid, -1.0]) for x in xs_mm])
    rendered = px[
        np.round(screen[:, 1] - box["y"]).astype(int), np.round(screen[:, 0] - box["x"]).astype(int)
    ]
    normals = np.asarray(Image.open(tiled.dir / "normals.png").convert("RGB"))
    theta, phi = np.radians(75), np.radians(90)
    light = np.array([np.sin(theta) * np.sin(phi), np.sin(theta) * np.cos(phi), -np.cos(theta)])
    cols = xs_mm * 1000 / f.pixel_size_um
    row = y_mid * 1000 / f.pixel_size_um
    full = relit_line(normals, cols, row, light)
    coarse_cols = np.round(cols / 4) * 4  # what the root tile's texels (every 4 px) would give
    coarse = relit_line(normals, coarse_cols, row, light)
    r_full = np.corrcoef(rendered, full)[0, 1]
    r_coarse = np.corrcoef(rendered, coarse)[0, 1]
    assert r_full > 0.95, (r_full, r_coarse)
    assert r_full > r_coarse + 0.01, (r_full, r_coarse)

    if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
        page.locator("#viewer").screenshot(
            path=str(Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"]) / "viewer-tiles-zoom.png")
        )

    # Two more zooms elsewhere: the cache stays within the budget and less than the whole
    # tileset was downloaded.
    for x, y in ((12.0, 6.0), (18.0, 12.0)):
        zoom_to(page, x, y, 8)
        s = wait_streamed(page)
        assert s["minPixelStep"] == 1, s
        assert s["bytesUsed"] <= s["budgetBytes"], s
    fetched = tile_bytes_fetched(page)
    assert fetched < tiled.full_bytes, (fetched, tiled.full_bytes)
    assert not errors, errors


def test_profile_reads_only_the_rows_it_touches(tiled_page, tiled, tools):
    """A height profile on a streamed model, drawn through the page's tool: heights from
    tiles/height.f32 by HTTP Range (never height.npy), the same values as height.npy, and far
    fewer bytes than the file."""
    page, errors = tiled_page
    f = tiled.facts
    page.evaluate("() => window.hammurabi.viewer.resetView()")
    wait_streamed(page)
    y = sum(f.groove_y_mm) / 2
    a, b = [f.groove_x_mm - 4, y, -1.5], [f.groove_x_mm + 4, y, -1.5]
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
        return { stats: h.reader.stats, start: part.start,
                 values: Array.from(part.grid.heightUm.slice(0, 8)) };
      }""",
        [a[:2], b[:2]],
    )
    height = np.load(tiled.dir / "height.npy")
    assert 0 < out["stats"]["bytesFetched"] < height.nbytes / 4, (out["stats"], height.nbytes)
    r0 = round((a[1] - out["start"][1]) * 1000 / f.pixel_size_um)
    np.testing.assert_allclose(out["values"], height[r0, :8], rtol=1e-6)
    page.keyboard.press("Escape")
    assert not errors, errors
