"""The library pages in a real browser against the real library service."""

from __future__ import annotations


def test_search_finds_a_tablet_and_opens_its_page(page, library):
    page.goto(f"{library.url}/index.html")
    page.wait_for_selector("body[data-total]")
    names = page.locator(".card .designation").all_inner_texts()
    assert {"P999001", "P999002", "P999003"} <= set(names)  # (+ tablets other tests create)
    # the tablet with a model shows its model's thumbnail.png, the others a placeholder
    first = page.locator(".card", has_text="P999001")
    first.locator("img").wait_for()
    assert "/assets/thumbnail.png" in first.locator("img").get_attribute("src")
    assert page.locator(".card", has_text="P999002").locator(".placeholder").count() == 1
    page.locator("#q").fill("P999002")
    page.locator("#search-form button[type=submit]").click()
    page.wait_for_function("() => document.querySelectorAll('.card').length === 1")
    card = page.locator(".card")
    assert "P999002" in card.inner_text()
    assert "Ur III" in card.inner_text()
    assert "q=P999002" in page.url  # the search is a link
    card.locator("a").click()
    page.wait_for_selector("#catalogue dd")
    assert page.locator("#title").inner_text() == "P999002"
    assert "Drehem" in page.locator("#catalogue").inner_text()
    assert page.locator("#empty").is_visible()  # no model for this one


def test_facets_count_and_filter(page, library):
    page.goto(f"{library.url}/index.html")
    page.wait_for_selector("button[data-facet='period']")
    ob = page.locator("button[data-facet='period'][data-value='Old Babylonian']")
    assert ob.locator(".count").inner_text() == "2"
    ob.click()
    page.wait_for_function("() => document.body.dataset.total === '2'")
    assert page.locator(".card").count() == 2
    assert "period=Old+Babylonian" in page.url or "period=Old%20Babylonian" in page.url
    has3d = page.locator("button[data-facet='has_3d'][data-value='true']")
    assert has3d.locator(".count").inner_text() == "1"
    has3d.click()
    page.wait_for_function("() => document.body.dataset.total === '1'")
    assert "P999001" in page.locator(".card").inner_text()


def test_tablet_page_lists_versions_downloads_and_links(page, library, tools):
    tools.open_tablet(page, library)
    options = page.locator("#model-select option").all_inner_texts()
    assert len(options) == 2 and all("obverse" in o for o in options)
    downloads = page.locator("#downloads").inner_text()
    for label in ("PLY", "GLB", "Height map"):
        if label == "PLY":
            continue  # the fixture model has no mesh.ply; its link appears only when it exists
        assert label in downloads
    hrefs = page.locator("#links a").evaluate_all("as => as.map(a => a.getAttribute('href'))")
    assert any(h.endswith("/iiif/manifest.json") for h in hrefs)
    assert "succeeded" in page.locator("#scans").inner_text()


def test_free_text_period_and_removable_filter_chips(page, library, tmp_path):
    page.goto(f"{library.url}/index.html?q=ur%20iii")
    page.wait_for_selector("body[data-total]")
    # "ur iii" is the period of P999002, not a word of its designation or museum number.
    assert "P999002" in page.locator(".card .designation").all_inner_texts()
    page.locator("button[data-facet='period'][data-value='Ur III']").click()
    page.wait_for_selector(".chip[data-chip='period']")
    chips = page.locator(".chip").all_inner_texts()
    assert any("ur iii" in c for c in chips) and any("Ur III" in c for c in chips)
    assert any("Clear all" in c for c in chips)
    # The chosen value heads its facet group and is visible.
    first = page.locator("[data-group='period'] button").first
    assert first.get_attribute("data-value") == "Ur III"
    assert first.get_attribute("aria-pressed") == "true"
    assert first.is_visible()
    page.screenshot(path=str(tmp_path / "library-filter-chips.png"))
    page.locator(".chip[data-chip='q']").click()
    page.wait_for_function("() => !document.querySelector(\".chip[data-chip='q']\")")
    assert "q=" not in page.url and "period=Ur" in page.url
    page.locator(".chip[data-chip='period']").click()
    page.wait_for_function("() => document.getElementById('chips').hidden")
    assert "period=" not in page.url
