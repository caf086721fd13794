"""Simulated data says so on the tablet page: a model made from simulated scans (its report
says ``simulated``; the API's ``simulated`` flag) shows the "Simulated scan" badge over the
viewer; a measured model does not."""

from __future__ import annotations

import json

import pytest

from .test_browser_tablet_model import TABLET, _add_tablet_model, _two_node_model_dir


@pytest.fixture(scope="module")
def simulated_library(tmp_path_factory, server_module):
    tmp = tmp_path_factory.mktemp("simulated_badge")
    lib = server_module.start_library(tmp / "lib")
    try:
        _two_node_model_dir(tmp / "whole")
        report = json.loads((tmp / "whole" / "report.json").read_text())
        (tmp / "whole" / "report.json").write_text(json.dumps({**report, "simulated": True}))
        lib.models["whole"] = _add_tablet_model(lib, tmp / "whole")
        yield lib
    finally:
        lib.stop()


def _wait_model(page, model_id: int) -> None:
    page.wait_for_function(
        "want => document.getElementById('viewer').dataset.loaded === want",
        arg=str(model_id),
        timeout=30000,
    )


def test_simulated_model_shows_the_badge_a_measured_one_does_not(page, simulated_library):
    lib = simulated_library
    page.goto(f"{lib.url}/tablet.html?id={lib.tablets[TABLET]}#m={lib.models['whole']}")
    _wait_model(page, lib.models["whole"])
    badge = page.locator("#simulated-badge")
    assert badge.is_visible()
    assert "Simulated scan" in badge.inner_text()
    box = badge.bounding_box()
    assert box is not None and box["width"] > 50 and box["height"] > 10
    # A face model without the flag (the seed's obverse, v2): no badge.
    first = next(iter(lib.tablets.values()))
    page.goto(f"{lib.url}/tablet.html?id={first}#m={lib.models['v2']}")
    _wait_model(page, lib.models["v2"])
    assert not page.locator("#simulated-badge").is_visible()
