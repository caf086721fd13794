"""A permalink that carries a measurement restores it; "Cite this view" names the tablet,
the model version, the view, the permalink and the access date; the profile CSV says what
it measured."""

from __future__ import annotations

import datetime as dt


def test_a_permalink_restores_the_distance_and_the_citation_names_it(browser, library, tools):
    context = browser.new_context(viewport={"width": 960, "height": 600})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        model = library.models["v2"]
        fragment = f"#m={model}&mt=d&ma=2,3,0&mb=14,8,0"
        tools.open_tablet(page, library, model="v2", fragment=fragment)
        readout = page.locator("#readout")
        assert readout.text_content().startswith("Distance: 13.00 mm")  # hypot(12, 5)
        # The page's own permalink keeps the measurement.
        link = page.evaluate("() => window.hammurabi.ui.permalinkUrl()")
        assert "mt=d" in link and "ma=2%2C3%2C0" in link and "mb=14%2C8%2C0" in link

        page.locator("#cite").click()
        text = page.locator("#cite-text").input_value()
        bibtex = page.locator("#cite-bibtex").input_value()
    finally:
        context.close()
    assert "P999001" in text and f"(model {model})" in text and "version" in text
    assert "distance 13.00 mm" in text and link in text
    assert f"accessed {dt.datetime.now(dt.UTC).date().isoformat()}" in text
    assert bibtex.startswith("@misc{P999001_m") and f"url = {{{link}}}" in bibtex
    assert not errors, errors


def test_a_screenshot_has_the_scale_bar_and_says_what_it_shows(browser, library, tools):
    import io
    from pathlib import Path

    import numpy as np
    from PIL import Image

    context = browser.new_context(viewport={"width": 960, "height": 600}, accept_downloads=True)
    page = context.new_page()
    try:
        tools.open_tablet(page, library, model="v2")
        page.locator("#shot-w").fill("640")
        page.locator("#shot-h").fill("400")
        with page.expect_download() as info:
            page.locator("#screenshot").click()
        data = Path(info.value.path()).read_bytes()
    finally:
        context.close()
    img = Image.open(io.BytesIO(data))
    assert img.format == "PNG" and img.size == (640, 400)
    text = img.text
    assert "(P999001), model " in text["Title"], text
    assert "version" in text["Title"] and "#m=" in text["Source"]
    assert text["Scale"].endswith("mm per pixel") and "mm bar" in text["Scale"]
    # The bar: a run of pure white pixels along its row, at the bottom left.
    px = np.asarray(img.convert("RGB"))
    bar_rows = px[300:400, :320]
    white = (bar_rows == 255).all(axis=-1)
    assert white.sum(axis=1).max() >= 20
