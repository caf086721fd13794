"""A model's licence and attribution set from the tablet page (issue 18, item 2): staff of the
holding institution set them, an invalid URI is refused with the API's message naming the
field, the citation carries the new values at once; a reader sees them but no form.

Its own library instance (the licence changes what the shared one shows).
Set HAMMURABI_SAVE_SCREENSHOTS=docs/screenshots to keep the screenshot."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

LICENCE = "https://creativecommons.org/licenses/by-nc/4.0/"
CREDIT = "Scan by the Test Museum laboratory"


@pytest.fixture(scope="module")
def own_library(server_module, tmp_path_factory):
    lib = server_module.start_library(tmp_path_factory.mktemp("licence"))
    yield lib
    lib.stop()


def test_staff_set_the_licence_and_the_citation_shows_it(page, own_library, server_module, tools):
    lib = own_library
    page.goto(f"{lib.url}/staff.html")
    page.locator("#email").fill(server_module.STAFF_EMAIL)
    page.locator("#password").fill(server_module.STAFF_PASSWORD)
    page.locator("#login-form button").click()
    page.wait_for_selector("#work:not([hidden])")
    tools.open_tablet(page, lib, model="v2")
    page.wait_for_selector("#licence-form:not([hidden])")
    before = page.locator("#licence-shown").inner_text()
    assert LICENCE not in before

    # Not a Creative Commons or RightsStatements URI: refused, the field named, nothing saved.
    page.fill("#licence-uri", "https://example.org/my-own-licence")
    page.click("#licence-save")
    page.wait_for_selector("#licence-error:not([hidden])")
    message = page.locator("#licence-error").inner_text()
    assert "not saved" in message and "licence" in message.split("saved")[1], message
    assert page.locator("#licence-shown").inner_text() == before

    page.fill("#licence-uri", LICENCE)
    page.fill("#licence-attribution", CREDIT)
    page.click("#licence-save")
    page.wait_for_function(
        "() => document.getElementById('licence-status').textContent === 'Saved.'"
    )
    assert page.locator("#licence-error").is_hidden()
    shown = page.locator("#licence-shown").inner_text()
    assert LICENCE in shown and CREDIT in shown and "own" in shown, shown
    if os.environ.get("HAMMURABI_SAVE_SCREENSHOTS"):
        page.locator("#licence").screenshot(
            path=str(Path(os.environ["HAMMURABI_SAVE_SCREENSHOTS"]) / "licence-form.png")
        )
    # The citation of this view carries it without a reload, and the API has it.
    page.locator("#cite").click()
    text = page.locator("#cite-text").input_value()
    assert f"Licence: {LICENCE}" in text and CREDIT in text, text
    record = page.evaluate(
        "id => fetch(`/api/v1/models/${id}`).then((r) => r.json())", lib.models["v2"]
    )
    assert record["licence"] == LICENCE and record["attribution"] == CREDIT
    # The other version keeps the tablet's.
    other = page.evaluate(
        "id => fetch(`/api/v1/models/${id}`).then((r) => r.json())", lib.models["v1"]
    )
    assert other["licence"] is None


def test_a_reader_sees_the_licence_but_no_form(browser, own_library, tools):
    context = browser.new_context(viewport={"width": 960, "height": 600})
    page = context.new_page()
    try:
        tools.open_tablet(page, own_library, model="v1")
        page.wait_for_selector("#licence:not([hidden])")
        assert page.locator("#licence-shown").inner_text()
        # The sign-in check has answered: nobody is signed in, and the form stays hidden.
        page.wait_for_selector("#licence[data-context='anonymous']", state="attached")
        assert page.locator("#licence-form").is_hidden()
        assert page.locator("#licence-save").is_hidden()
    finally:
        context.close()
