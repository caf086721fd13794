"""The whole-tablet model (registration: one glTF node per scanned face, scan_id null) on the
tablet page: offered as "Whole tablet", one checkbox per face, hiding a face redraws the
canvas without it, and the fatcross plates are linked; the permalink records the hidden faces
and a reload restores them.

Its own library instance: a tablet-level model would change the shared fixture's facet counts
(has_3d) that test_browser_library.py checks."""

from __future__ import annotations

import json
import math
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest

BACKGROUND = np.array([0x1D, 0x1F, 0x24]) / 255  # the viewer's clear colour
TABLET = "P999003"  # no face models in the seed: the whole tablet is what the page shows


def _two_node_model_dir(model_dir: Path) -> None:
    """model.glb with nodes "obverse" (x < 0) and "reverse" (x > 0): two 18 × 30 × 4 mm slabs
    side by side in the tablet frame (mm), plus report.json and one fatcross plate."""
    import trimesh
    from PIL import Image

    scene = trimesh.Scene()
    obverse = trimesh.creation.box(extents=(18.0, 30.0, 4.0))
    obverse.apply_translation((-11.0, 0.0, 0.0))
    scene.add_geometry(obverse, node_name="obverse", geom_name="obverse")
    # Like worker/register's scene: the reverse's node carries its scan → tablet transform
    # (turned over the y axis, then moved right), its mesh stays in its own frame.
    turned = trimesh.transformations.rotation_matrix(np.pi, (0.0, 1.0, 0.0))
    turned[:3, 3] = (11.0, 0.0, 0.0)
    reverse = trimesh.creation.box(extents=(18.0, 30.0, 4.0))
    scene.add_geometry(reverse, node_name="reverse", geom_name="reverse", transform=turned)
    model_dir.mkdir(parents=True)
    (model_dir / "model.glb").write_bytes(scene.export(file_type="glb"))
    (model_dir / "report.json").write_text(json.dumps({"scans": ["obverse", "reverse"]}))
    (model_dir / "fatcross").mkdir()
    Image.new("RGB", (8, 8), (200, 180, 150)).save(model_dir / "fatcross" / "P999003.png")


def _add_tablet_model(library, model_dir: Path) -> int:
    """A succeeded registration job of TABLET storing ``model_dir``, as the worker stores it."""
    return library.add_tablet_model(TABLET, model_dir)


@pytest.fixture(scope="module")
def tablet_library(tmp_path_factory, server_module):
    tmp = tmp_path_factory.mktemp("tablet_model")
    lib = server_module.start_library(tmp / "lib")
    try:
        _two_node_model_dir(tmp / "whole")
        lib.models["whole"] = _add_tablet_model(lib, tmp / "whole")
        yield lib
    finally:
        lib.stop()


def _wait_loaded(page, lib, tools) -> None:
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want",
        arg=str(lib.models["whole"]),
        timeout=30000,
    )
    tools.settle(page)


def _on_model(px):
    return np.abs(px - BACKGROUND).sum(axis=-1) > 0.05


def _band(px):
    """The middle third of the rows: clear of the notice (top) and the scale bar (bottom),
    which are drawn over the canvas; the 30 mm tall slabs span it."""
    h = px.shape[0]
    return px[h // 3 : 2 * h // 3]


def _right_half_covered(page, tools) -> float:
    """Share of the right half showing a model: the reverse slab (x > 0) in the obverse view."""
    px = _band(tools.canvas_pixels(page))
    return _on_model(px[:, px.shape[1] // 2 + 4 :]).mean()


def _checked(page) -> dict[str, bool]:
    return dict(
        page.locator("#faces input[type=checkbox]").evaluate_all(
            "bs => bs.map(b => [b.dataset.face, b.checked])"
        )
    )


def test_whole_tablet_faces_toggle(page, tablet_library, tools):
    lib = tablet_library
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}")
    _wait_loaded(page, lib, tools)
    options = page.locator("#model-select option").all_inner_texts()
    assert any(o.startswith("Whole tablet") for o in options), options
    boxes = page.locator("#faces input[type=checkbox]")
    assert boxes.count() == 2
    assert sorted(boxes.evaluate_all("bs => bs.map(b => b.dataset.face)")) == [
        "obverse",
        "reverse",
    ]
    plates = page.locator("#faces a").evaluate_all("as => as.map(a => a.getAttribute('href'))")
    assert any(h.endswith("/assets/fatcross/P999003.png") for h in plates), plates
    # No normals.png on the whole tablet: the page says it is lit by the mesh normals.
    assert "mesh normals" in page.locator("#notice").inner_text()

    pick = "([x, y]) => window.hammurabi.viewer.pick(x, y)"
    reverse_centre = tools.screen_of(page, (11.0, 0.0, -2.0))  # its face toward the camera
    hit = page.evaluate(pick, list(reverse_centre))
    assert hit is not None and abs(hit["point"][0] - 11.0) < 0.5, hit
    before = _band(tools.canvas_pixels(page))
    page.locator("#faces input[data-face='reverse']").uncheck()
    tools.settle(page)
    after = _band(tools.canvas_pixels(page))
    assert page.evaluate(pick, list(reverse_centre)) is None  # hidden faces are not picked
    w = before.shape[1]
    # The obverse view has x to the right: the reverse slab (x > 0) fills part of the right
    # half before and none of it after; the obverse slab (left half) is drawn as before.
    right_before = _on_model(before[:, w // 2 + 4 :]).mean()
    right_after = _on_model(after[:, w // 2 + 4 :]).mean()
    assert right_before > 0.1, f"the reverse slab covers only {right_before:.1%} before"
    assert right_after < 0.01, f"{right_after:.1%} of the right half still shows a model"
    left_changed = np.abs(after[:, : w // 2 - 4] - before[:, : w // 2 - 4]).max()
    assert left_changed < 0.02, f"the obverse half changed by {left_changed:.3f}"
    assert page.evaluate("() => window.hammurabi.viewer.partNames().length") == 2


def _same_link(a: str, b: str) -> bool:
    """Same page and fragment parameters, numbers equal to 1e-6 (relative) or 1e-9 (absolute)."""
    (base_a, _, frag_a), (base_b, _, frag_b) = a.partition("#"), b.partition("#")
    pa, pb = frag_a.split("&"), frag_b.split("&")
    if base_a != base_b or len(pa) != len(pb):
        return False
    for x, y in zip(pa, pb, strict=True):
        if x == y:
            continue
        (kx, _, vx), (ky, _, vy) = x.partition("="), y.partition("=")
        nx, ny = unquote(vx).split(","), unquote(vy).split(",")
        if kx != ky or len(nx) != len(ny):
            return False
        try:
            if not all(
                math.isclose(float(u), float(v), rel_tol=1e-6, abs_tol=1e-9)
                for u, v in zip(nx, ny, strict=True)
            ):
                return False
        except ValueError:
            return False
    return True


def test_whole_tablet_permalink_restores_hidden_faces(page, tablet_library, tools):
    lib = tablet_library
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}")
    _wait_loaded(page, lib, tools)
    assert _right_half_covered(page, tools) > 0.1
    page.locator("#faces input[data-face='reverse']").uncheck()
    # The page writes the state into the fragment a moment after each change.
    page.wait_for_function("() => location.hash.includes('hide=reverse')", timeout=10000)
    link = page.url
    assert f"m={lib.models['whole']}" in link
    # The permalink button (K) gives the same state, model version included.
    button_link = page.evaluate("() => window.hammurabi.ui.permalink()")
    assert "hide=reverse" in button_link and f"m={lib.models['whole']}" in button_link

    page.reload()
    _wait_loaded(page, lib, tools)
    # Floats in the view state may round differently when written again (…054e-15 vs …055e-15).
    assert _same_link(page.url, link), (page.url, link)
    assert _checked(page) == {"obverse": True, "reverse": False}
    assert page.evaluate("() => window.hammurabi.viewer.getState().hidden") == ["reverse"]
    assert _right_half_covered(page, tools) < 0.01, "the reverse is drawn after the reload"
    assert page.locator("#notice").inner_text().count("could not be used") == 0

    # A link naming faces this model lacks (another version, a hand edit) keeps the rest, says
    # which it ignored, and does not break the page (the page fixture fails on page errors).
    page.goto("about:blank")  # else a goto that changes only the fragment does not reload
    page.goto(link.replace("hide=reverse", "hide=left&hide=reverse&hide=%01"))
    _wait_loaded(page, lib, tools)
    assert _checked(page) == {"obverse": True, "reverse": False}
    notice = page.locator("#notice").inner_text()
    assert 'face "left"' in notice and "hide" in notice, notice
    assert "mesh normals" in notice, notice  # the model's own notice stays

    # Showing the face again takes it out of the link.
    page.locator("#faces input[data-face='reverse']").check()
    page.wait_for_function("() => !location.hash.includes('hide=')", timeout=10000)
    tools.settle(page)
    assert _right_half_covered(page, tools) > 0.1
