"""/docs and /docs/redoc in Chromium with every request beyond this machine blocked: the API
documentation must come from our own files (issue 18: it was blank without internet)."""

from __future__ import annotations

from urllib.parse import urlsplit

LOOPBACK = {"127.0.0.1", "localhost", "::1", "[::1]"}


def _offline(context, blocked: list[str]) -> None:
    def route(r):
        host = urlsplit(r.request.url).hostname or ""
        if r.request.url.startswith(("data:", "blob:")) or host in LOOPBACK:
            r.continue_()
        else:
            blocked.append(r.request.url)
            r.abort()

    context.route("**/*", route)


def test_swagger_ui_and_redoc_work_offline(browser, library):
    context = browser.new_context()
    blocked: list[str] = []
    _offline(context, blocked)
    errors: list[str] = []
    page = context.new_page()
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on(
        "console",
        lambda msg: errors.append(msg.text) if "Content Security Policy" in msg.text else None,
    )
    try:
        page.goto(f"{library.url}/docs")
        # Swagger UI renders one .opblock per operation once it has read the schema.
        page.wait_for_selector(".opblock", timeout=30_000)
        operations = page.locator(".opblock").count()
        assert operations > 20
        assert page.locator(".opblock-summary-path", has_text="/iiif/manifest.json").count() >= 1

        page.goto(f"{library.url}/docs/redoc")
        page.wait_for_selector("[data-section-id^='tag/']", timeout=30_000)
        assert page.get_by_text("/iiif/3d/manifest.json").count() >= 1
    finally:
        context.close()
    assert not blocked, blocked
    # ReDoc's sidebar credit asked cdn.redoc.ly for its logo and the CSP refused it; our
    # copy of the script (backend/docs.py) names a local image, so no refusal at all.
    assert errors == []
