"""The photograph beside the render on a whole tablet (issue 20, item 1) and each face's
measured gloss (item 7): the registration's whole-tablet files (`whole_tablet_model`) for two
faces of the simulator's tablet at their true poses, each face model carrying its scan's
photographs (photos/index.json + JPEGs, as worker.photos writes them) and the obverse a gloss.

The photographs are the ground truth's Lambertian image (albedo · max(0, n·l)) under eight
lights in each face's own scan frame: what a camera sees of a matte tablet, with the lights'
directions known exactly, so a light turned into the wrong frame picks a photograph lit from
the wrong side, and a misplaced swipe does not line up.

Set HAMMURABI_SAVE_SCREENSHOTS=docs/screenshots to keep the screenshots."""

from __future__ import annotations

import io
import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

TABLET = "P999003"  # the seeded tablet without models of its own
server = sys.modules["hammurabi_browser_server"]  # loaded by conftest.py
FACES = ["obverse", "reverse"]
SIZE = (120, 96)
AZIMUTHS = [0, 45, 90, 135, 180, 225, 270, 315]
POLAR = 60.0
SHOTS = (
    Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"])
    if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS")
    else None
)


def _photographs(d: Path) -> None:
    """photos/index.json and one JPEG per light, as worker.photos writes them."""
    from worker.photos import _jpeg
    from worker.recon.color import linear_to_srgb8
    from worker.recon.photometric import light_directions

    normals = np.nan_to_num(np.load(d / "normals.npy"))
    mask = np.asarray(Image.open(d / "mask.png")) > 127
    srgb = np.asarray(Image.open(d / "albedo.png").convert("RGB"), np.float32) / 255
    albedo = srgb**2.2
    lights = light_directions(AZIMUTHS, POLAR)
    (d / "photos").mkdir()
    entries = []
    for az, light in zip(AZIMUTHS, lights, strict=True):
        shade = np.clip(normals @ light, 0, None)[..., None] * albedo
        shade[~mask] = 0
        name = f"photos/{len(entries):03d}-color-az{az:05.1f}.jpg"
        (d / name).write_bytes(_jpeg(linear_to_srgb8(np.clip(shade, 0, 1).astype(np.float32))))
        entries.append(
            {
                "file": name,
                "kind": "color",
                "azimuth_deg": float(az),
                "polar_deg": POLAR,
                "light": [round(float(v), 6) for v in light],
            }
        )
    h, w = mask.shape
    index = {"version": 1, "source_size_px": [w, h], "size_px": [w, h], "photos": entries}
    (d / "photos" / "index.json").write_text(json.dumps(index))


def _gloss(d: Path) -> None:
    """A strong, uniform measured gloss (worker.photos' encoding: red = k_s / strength_scale)."""
    mask = np.asarray(Image.open(d / "mask.png")) > 127
    png = np.zeros((*mask.shape, 3), np.uint8)
    png[..., 0] = 255
    png[..., 1] = 255
    Image.fromarray(png).save(d / "gloss.png")
    (d / "gloss.json").write_text(json.dumps({"strength_scale": 0.5, "exponent": 16.0}))


def _whole_tablet(out: Path, *, gloss: bool, tiled: bool = False) -> Path:
    """The worker's whole-tablet files, with transforms.json and report.json as the
    registration writes them (the true poses instead of the fitted ones); ``tiled``: with
    its tiles too (worker.tiles.tablet), so the page streams it."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "worker" / "register"))
    try:
        from synthetic import write_gt_model_dirs
    finally:
        sys.path.pop(0)
    from worker.register.io import face_asset_dir, load_model_dir, write_output_dir
    from worker.register.run import whole_tablet_model

    paths, truths = write_gt_model_dirs(out / "faces", size=SIZE, faces=FACES)
    for p in paths:
        _photographs(p)
    if gloss:
        _gloss(paths[0])  # the obverse only
    loaded = [load_model_dir(p) for p in paths]
    files = whole_tablet_model(loaded, truths)
    files["transforms.json"] = json.dumps(
        {
            "scans": {
                c.label: {"rotation": t[:3, :3].tolist(), "translation_mm": t[:3, 3].tolist()}
                for (c, _), t in zip(loaded, truths, strict=True)
            }
        }
    ).encode()
    files["report.json"] = json.dumps(
        {
            "scans": [c.label for c, _ in loaded],
            "faces": {
                c.label: {
                    "assets": face_asset_dir(c.label),
                    "face": c.face,
                    "pixel_size_um": raw["pixel_size_um"],
                }
                for c, raw in loaded
            },
        }
    ).encode()
    model = write_output_dir(out / "model", files)
    if tiled:
        from worker.assets import derive_assets
        from worker.tiles.tablet import build_tablet_tiles

        for p in paths:
            derive_assets(p)  # the tiles carry each face's curvature and accessibility

        build_tablet_tiles(
            model,
            {
                face_asset_dir(c.label): (Path(p), np.asarray(t, float))
                for (c, _), p, t in zip(loaded, paths, truths, strict=True)
            },
        )
    return model


@pytest.fixture(scope="module")
def photo_tablet(tmp_path_factory, server_module):
    tmp = tmp_path_factory.mktemp("whole_photos")
    lib = server_module.start_library(tmp / "lib")
    try:
        lib.models["matte"] = lib.add_tablet_model(TABLET, _whole_tablet(tmp / "m", gloss=False))
        lib.models["glossy"] = lib.add_tablet_model(TABLET, _whole_tablet(tmp / "g", gloss=True))
        lib.models["streamed"] = lib.add_tablet_model(
            TABLET, _whole_tablet(tmp / "s", gloss=True, tiled=True)
        )
        yield lib
    finally:
        lib.stop()


def _open(page, lib, label: str) -> None:
    page.goto("about:blank")  # another model of the same page: a fragment alone does not reload
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}#m={lib.models[label]}")
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want"
        " || document.getElementById('tablet-error').textContent",
        arg=str(lib.models[label]),
        timeout=60000,
    )
    assert not page.locator("#tablet-error").inner_text(), page.locator(
        "#tablet-error"
    ).inner_text()
    assert page.locator("#viewer").get_attribute("data-loaded") == str(lib.models[label])
    page.evaluate("() => window.hammurabi.viewer.whenIdle()")


def _caption(page) -> str:
    return page.locator("#photo-caption").inner_text()


def _azimuth(page) -> float:
    return float(re.search(r"azimuth (-?\d+)°", _caption(page)).group(1))


def _grey(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=float)


def _view(page, view: str) -> None:
    page.evaluate("v => window.hammurabi.viewer.setView(v)", view)


def test_the_photograph_of_the_face_in_view_under_its_own_light(page, photo_tablet):
    lib = photo_tablet
    _open(page, lib, "matte")
    page.wait_for_function("() => !document.getElementById('photo-controls').hidden", timeout=20000)
    page.check("#photo-show")
    for view in FACES:
        _view(page, view)
        assert _caption(page).startswith(f"Face sim-0-{view}:"), (view, _caption(page))
        assert page.locator("#photo-panel").get_attribute("data-face") == f"sim-0-{view}"
        # Opposite raking presets pick photographs of that face taken from opposite sides.
        page.locator("#raking button").nth(2).click()
        first = _azimuth(page)
        page.locator("#raking button").nth(6).click()
        second = _azimuth(page)
        assert abs(((first - second) % 360) - 180) < 1, (view, first, second)
    if SHOTS:
        page.wait_for_function(
            "() => { const i = document.getElementById('photo-img'); return i.complete && i.naturalWidth > 0; }"
        )
        page.screenshot(path=str(SHOTS / "whole-tablet-photo-beside.png"))

    # The reverse under its photograph's light, the photograph swiped over it: aligned and
    # alike (a light in the wrong frame would shade the render from another side).
    _view(page, "reverse")
    page.locator("#raking button").nth(2).click()
    page.click("#photo-use-light")
    assert "the same light as the render" in _caption(page), _caption(page)
    assert _caption(page).startswith("Face sim-0-reverse:")
    page.evaluate("() => window.hammurabi.viewer.setShading({ mode: 'natural' })")
    page.uncheck("#photo-show")
    page.check("#photo-swipe")
    page.check("#photo-show")
    page.wait_for_function(
        "() => { const i = document.getElementById('photo-layer-img'); return i.complete && i.naturalWidth > 0; }"
    )
    assert page.evaluate("() => window.hammurabi.viewer.getState().camera.position[2]") > 0
    page.evaluate("() => window.hammurabi.viewer.whenIdle()")
    stage = page.locator("#viewer").bounding_box()
    swipe_at = {}
    for at in ("100", "0"):
        page.fill("#photo-swipe-at", at)
        page.dispatch_event("#photo-swipe-at", "input")
        page.wait_for_timeout(300)
        swipe_at[at] = _grey(page.screenshot(clip=stage))
    render, photo = swipe_at["100"], swipe_at["0"]
    if SHOTS:
        page.fill("#photo-swipe-at", "50")
        page.dispatch_event("#photo-swipe-at", "input")
        page.wait_for_timeout(300)
        page.screenshot(path=str(SHOTS / "whole-tablet-photo-swipe.png"))
    box = page.locator("#photo-layer-img").bounding_box()
    assert box["width"] > 0.3 * stage["width"]
    tablet = (render > 30) & (photo > 30)
    assert tablet.mean() > 0.05
    gx_r, gx_p = np.gradient(render, axis=1)[tablet], np.gradient(photo, axis=1)[tablet]
    corr = np.corrcoef(gx_r, gx_p)[0, 1]
    assert corr > 0.5, corr
    shifted = np.roll(photo, 6, axis=1)  # misaligned by a few pixels: much less alike
    assert np.corrcoef(gx_r, np.gradient(shifted, axis=1)[tablet])[0, 1] < corr - 0.2


def _face_brightness(page, tools, view: str) -> float:
    page.evaluate(
        """view => {
        const v = window.hammurabi.viewer;
        v.setShading({ mode: 'natural' });
        v.setLight({ follow: true, azimuthDeg: 0, polarDeg: 0, intensity: 1, ambient: 0.1, gloss: 0 });
        v.setView(view);
      }""",
        view,
    )
    tools.idle(page)
    server.settle_tiles(page)  # a streamed tablet: its tiles in, then drawn
    px = tools.render_pixels(page, 240, 160)
    grey = px.mean(axis=-1)
    on = grey > 0.08
    assert on.mean() > 0.05
    return float(grey[on].mean())


def test_each_face_shines_with_its_own_measured_gloss(page, photo_tablet, tools):
    lib = photo_tablet
    got = {}
    for label in ("matte", "glossy"):
        _open(page, lib, label)
        has = page.evaluate(
            "() => window.hammurabi.viewer.model.partMaterials.map((m) => m.uniforms.uHasGlossMap.value)"
        )
        assert has == ([True, False] if label == "glossy" else [False, False]), (label, has)
        got[label] = {v: _face_brightness(page, tools, v) for v in FACES}
        if SHOTS and label == "glossy":
            _face_brightness(page, tools, "obverse")
            px = tools.render_pixels(page, 360, 240)
            Image.fromarray(np.rint(px * 255).astype(np.uint8)).save(
                SHOTS / "whole-tablet-gloss-obverse.png"
            )
    # The light from the camera: the glossy obverse shines, its reverse (no gloss) does not.
    assert got["glossy"]["obverse"] > got["matte"]["obverse"] + 0.02, got
    assert got["glossy"]["reverse"] == pytest.approx(got["matte"]["reverse"], abs=0.01), got


def test_the_streamed_tablet_has_the_photographs_and_gloss_of_its_faces(page, photo_tablet, tools):
    """The same tablet streamed: the photograph of the face in view, and each face's gloss
    from its tiles (`dh_maps.gloss`) shining as model.glb's faces do."""
    lib = photo_tablet
    _open(page, lib, "streamed")
    assert page.evaluate("() => window.hammurabi.viewer.streaming() !== null")
    page.wait_for_function("() => !document.getElementById('photo-controls').hidden", timeout=20000)
    page.check("#photo-show")
    for view in FACES:
        _view(page, view)
        server.settle_tiles(page)
        page.evaluate("() => window.hammurabi.viewer.setLight({ azimuthDeg: 33 })")  # refresh
        assert _caption(page).startswith(f"Face sim-0-{view}:"), (view, _caption(page))
    page.uncheck("#photo-show")
    streamed = {v: _face_brightness(page, tools, v) for v in FACES}
    _open(page, lib, "glossy")
    mesh = {v: _face_brightness(page, tools, v) for v in FACES}
    for v in FACES:
        assert streamed[v] == pytest.approx(mesh[v], abs=0.02), (streamed, mesh)
