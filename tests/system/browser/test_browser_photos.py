"""The photograph beside the render (issue 20, item 1) and the measured gloss (item 7) on a
real reconstruction: a simulated glossy scan, reconstructed, its photographs kept by
worker.photos, served by the library, shown by the tablet page."""

from __future__ import annotations

import io
import os
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from worker.photos import write_photo_assets
from worker.pipeline import reconstruct_bundle
from worker.simulate import simulate_scan

TABLET = "P999002"
SHOTS = (
    Path(os.environ.get("HAMMURABI_SAVE_SCREENSHOTS", ""))
    if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS")
    else None
)


@pytest.fixture(scope="module")
def photo_library(tmp_path_factory, server_module):
    tmp = tmp_path_factory.mktemp("photos")
    simulate_scan(tmp / "sim", seed=2, preset="quick", size=(240, 180), physics="glossy-dark")
    reconstruct_bundle(tmp / "sim" / "bundle", tmp / "model")
    write_photo_assets(tmp / "sim" / "bundle", tmp / "model")
    lib = server_module.start_library(
        tmp / "lib", extra_models=[("photo", TABLET, "obverse", tmp / "model")]
    )
    yield lib
    lib.stop()


def _open(page, lib):
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}#m={lib.models['photo']}")
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want",
        arg=str(lib.models["photo"]),
        timeout=60000,
    )
    page.wait_for_function("() => !document.getElementById('photo-controls').hidden", timeout=20000)


def _azimuth(page) -> float:
    text = page.locator("#photo-caption").inner_text()
    return float(re.search(r"azimuth (-?\d+)°", text).group(1))


def _grey(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=float)


def test_the_photograph_follows_the_light_and_matches_the_render(page, photo_library):
    lib = photo_library
    _open(page, lib)
    page.check("#photo-show")
    page.wait_for_function(
        "() => { const i = document.getElementById('photo-img'); return i.complete && i.naturalWidth > 0; }"
    )
    assert page.locator("#photo-panel").is_visible()
    # Opposite raking presets pick photographs taken from opposite sides.
    page.locator("#raking button").nth(2).click()
    first = _azimuth(page)
    page.locator("#raking button").nth(6).click()
    second = _azimuth(page)
    assert abs(((first - second) % 360) - 180) < 1, (first, second)
    if SHOTS:
        page.screenshot(path=str(SHOTS / "viewer-photo-beside.png"))

    # The render under the photograph's own light, and the photograph swiped over it in
    # the face view: aligned, and alike (what the camera saw is what the model shows).
    page.click("#photo-use-light")
    assert "the same light as the render" in page.locator("#photo-caption").inner_text()
    page.uncheck("#photo-show")
    page.check("#photo-swipe")
    page.check("#photo-show")
    page.wait_for_function(
        "() => { const i = document.getElementById('photo-layer-img'); return i.complete && i.naturalWidth > 0; }"
    )
    stage = page.locator("#viewer").bounding_box()
    page.fill("#photo-swipe-at", "100")
    page.dispatch_event("#photo-swipe-at", "input")
    page.wait_for_timeout(300)
    render = _grey(page.screenshot(clip=stage))
    page.fill("#photo-swipe-at", "0")
    page.dispatch_event("#photo-swipe-at", "input")
    page.wait_for_timeout(300)
    photo = _grey(page.screenshot(clip=stage))
    if SHOTS:
        page.fill("#photo-swipe-at", "50")
        page.dispatch_event("#photo-swipe-at", "input")
        page.wait_for_timeout(300)
        page.screenshot(path=str(SHOTS / "viewer-photo-swipe.png"))
    box = page.locator("#photo-layer-img").bounding_box()
    assert box["width"] > 0.3 * stage["width"]  # placed over the model, not a thumbnail
    # Compare where the tablet is (bright in both), on gradients: the wedges' light and shade.
    tablet = (render > 40) & (photo > 40)
    assert tablet.mean() > 0.1
    gx_r, gx_p = np.gradient(render, axis=1)[tablet], np.gradient(photo, axis=1)[tablet]
    corr = np.corrcoef(gx_r, gx_p)[0, 1]
    assert corr > 0.5, corr
    # Misaligned by a few pixels, the same images correlate much less: the test can fail.
    shifted = np.roll(photo, 6, axis=1)
    gx_s = np.gradient(shifted, axis=1)[tablet]
    assert np.corrcoef(gx_r, gx_s)[0, 1] < corr - 0.2
