"""Fixtures of the browser tests: the real library service with seeded tablets and models
(see server.py), Debian's chromium driven by Playwright, and helpers to read the viewer.

All browser tests share one server and one browser per xdist worker (group "browser")."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "hammurabi_browser_server", Path(__file__).with_name("server.py")
)
server = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = server
_spec.loader.exec_module(server)


def pytest_collection_modifyitems(items):
    here = Path(__file__).parent
    for item in items:
        if Path(str(item.fspath)).is_relative_to(here):
            item.add_marker(pytest.mark.browser)
            item.add_marker(pytest.mark.xdist_group("browser"))


@pytest.fixture(scope="session")
def server_module():
    """server.py: constants such as STAFF_EMAIL and UPLOAD_CHUNK_BYTES."""
    return server


@pytest.fixture(scope="session")
def library(tmp_path_factory):
    lib = server.start_library(tmp_path_factory.mktemp("library"))
    yield lib
    lib.stop()


@pytest.fixture(scope="session")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = server.launch_chromium(p)
        yield b
        b.close()


def watch_csp(pg, errors: list[str]) -> None:
    """A resource the Content-Security-Policy blocks (backend/headers.py) fails the test."""
    pg.on(
        "console",
        lambda msg: errors.append(msg.text) if "Content Security Policy" in msg.text else None,
    )


VIEWPORT = {"width": 960, "height": 600}  # small: SwiftShader renders every pixel on the CPU


@pytest.fixture
def page(browser):
    context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    watch_csp(pg, errors)
    yield pg
    context.close()
    assert not errors, f"uncaught errors in the page: {errors}"


@pytest.fixture(scope="module")
def _viewer_page_module(browser, library):
    """One tablet page for a module's viewer tests: loading it costs seconds in SwiftShader."""
    context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda exc: errors.append(str(exc)))
    watch_csp(pg, errors)
    open_tablet(pg, library)
    yield pg, errors
    context.close()


@pytest.fixture
def viewer_page(_viewer_page_module):
    """The shared tablet page, reset to the default light, shading and framing."""
    pg, errors = _viewer_page_module
    pg.evaluate(
        """() => {
        const { viewer, ui } = window.hammurabi;
        ui.stopTools();
        viewer.setState({ light: { azimuthDeg: 315, polarDeg: 45, intensity: 1, ambient: 0.15,
          gloss: 0 }, shading: { mode: 'natural', curvatureScale: 0, exaggeration: 2 } });
        viewer.setProjection('orthographic');
        viewer.resetView();
        const r = document.getElementById('readout');
        r.textContent = ''; delete r.dataset.distanceMm;
      }"""
    )
    settle(pg)
    yield pg
    assert not errors, f"uncaught errors in the page: {errors}"


@pytest.fixture
def tools():
    """Helpers to drive and read the viewer (see the functions below)."""
    from types import SimpleNamespace

    return SimpleNamespace(
        open_tablet=open_tablet,
        settle=settle,
        canvas_pixels=canvas_pixels,
        screen_of=screen_of,
        render_pixels=render_pixels,
        idle=idle,
    )


def open_tablet(page, library, *, model: str | None = None, fragment: str = "") -> None:
    """Open the first tablet's page and wait until the viewer has drawn its model."""
    tablet_id = library.tablets["P999001"]
    frag = fragment or (f"#m={library.models[model]}" if model else "")
    page.goto(f"{library.url}/tablet.html?id={tablet_id}{frag}")
    want = str(library.models[model]) if model else None
    page.wait_for_function(
        "want => { const c = document.getElementById('viewer');"
        " return c.dataset.loaded && (!want || c.dataset.loaded === want); }",
        arg=want,
        timeout=30000,
    )
    settle(page)


def settle(page) -> None:
    """Wait for lazily loaded maps and two animation frames, so the canvas shows the state."""
    page.evaluate(
        "async () => { await window.hammurabi.viewer.whenIdle();"
        " await new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r))); }"
    )


def idle(page) -> None:
    """Wait for lazily loaded maps only (enough before render_pixels, which draws itself)."""
    page.evaluate("() => window.hammurabi.viewer.whenIdle()")


def canvas_pixels(page):
    """The viewer canvas as an (H, W, 3) float array in [0, 1], as composited on screen."""
    import io

    import numpy as np
    from PIL import Image

    png = page.locator("#viewer").screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255


def screen_of(page, point_mm) -> tuple[float, float]:
    """Page (CSS pixel) position of a model point in mm, from the viewer's own camera."""
    p = page.evaluate("p => window.hammurabi.viewer.project(p)", list(point_mm))
    return p["x"], p["y"]


def render_pixels(page, width: int = 360, height: int = 240):
    """The current view rendered off-screen by the viewer's own screenshot() at a small size,
    as an (H, W, 3) float array in [0, 1] (cheaper than a page screenshot in SwiftShader)."""
    import base64
    import io

    import numpy as np
    from PIL import Image

    data_url = page.evaluate(
        """async ([w, h]) => {
        const blob = await window.hammurabi.viewer.screenshot({ width: w, height: h });
        return await new Promise((resolve) => {
          const r = new FileReader(); r.onload = () => resolve(r.result); r.readAsDataURL(blob);
        });
      }""",
        [width, height],
    )
    png = base64.b64decode(data_url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255
