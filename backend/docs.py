"""The API's documentation pages, served from our own files so they work offline.

``/docs`` is Swagger UI and ``/docs/redoc`` ReDoc; their scripts and styles (the
``fastapi-offline`` package's copies of swagger-ui-dist and redoc) are served under
``/docs/static``, with our own start-up script instead of an inline one so the pages keep
a strict Content-Security-Policy (backend/headers.py, ``DOCS_CSP``). The OpenAPI document
describes the error bodies we really send (:func:`describe_errors`).
"""

from __future__ import annotations

from functools import cache
from html import escape
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from backend.schemas import ErrorOut, ValidationErrorOut

DOCS_PATH = "/docs"
VENDOR_DIR = Path(fastapi_offline.__file__).parent / "static"
OWN_DIR = Path(__file__).parent / "docs_static"
# ReDoc's sidebar credit shows Redocly's logo from their CDN, which the docs CSP refuses (a
# console error on every visit) and which offline machines cannot reach: our copy of the
# script names a small local image instead.
REDOC_CDN_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
REDOC_LOCAL_LOGO = f"{DOCS_PATH}/static/own/redoc-logo.svg"


def _page(title: str, head: str, body: str) -> HTMLResponse:
    return HTMLResponse(
        "<!doctype html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<title>{escape(title)}</title>"
        f"<link rel='icon' type='image/png' href='{DOCS_PATH}/static/vendor/favicon.png'>"
        f"{head}</head>{body}</html>"
    )


@cache
def redoc_script() -> bytes:
    """The vendored ReDoc bundle with its one CDN image (the credit's logo) made local."""
    script = (VENDOR_DIR / "redoc.standalone.js").read_bytes()
    return script.replace(REDOC_CDN_LOGO.encode(), REDOC_LOCAL_LOGO.encode())


def describe_errors(schema: dict) -> dict:
    """``schema`` with FastAPI's default 422 body replaced by the one we send.

    FastAPI documents ``{"detail": [{"loc", "msg", "type"}]}``; backend.errors answers
    ``{"detail": str, "where": str | null, "problems": [{"where", "message"}]}``.
    """
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    validation = ValidationErrorOut.model_json_schema(ref_template="#/components/schemas/{model}")
    for name, definition in validation.pop("$defs", {}).items():
        components[name] = definition
    components["HTTPValidationError"] = validation
    components.pop("ValidationError", None)
    components["ErrorOut"] = ErrorOut.model_json_schema()
    # Every error (401, 403, 404, 405, 409, 413, 416, 429...) has the same body: documented
    # once per operation as its ``default`` response rather than guessed code by code.
    default = {
        "description": "an error: a message and the culprit",
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}},
    }
    for item in schema.get("paths", {}).values():
        for operation in item.values():
            if isinstance(operation, dict) and "responses" in operation:
                operation["responses"].setdefault("default", default)
    return schema


def set_maximum(schema: dict, path: str, parameter: str, maximum: int) -> None:
    """Document a limit that comes from the settings (a route's ``Query`` cannot know it)."""
    for param in schema.get("paths", {}).get(path, {}).get("get", {}).get("parameters", []):
        if param.get("name") == parameter:
            param["schema"]["maximum"] = maximum


def install_docs(
    app: FastAPI, *, openapi_url: str, title: str, limits: dict[tuple[str, str], int]
) -> None:
    """Routes of the documentation pages and the OpenAPI document with our error bodies;
    ``limits``: (path, query parameter) → the maximum the route enforces."""

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = get_openapi(title=app.title, version=app.version, routes=app.routes)
            for (path, parameter), maximum in limits.items():
                set_maximum(schema, path, parameter, maximum)
            app.openapi_schema = describe_errors(schema)
        return app.openapi_schema

    app.openapi = openapi
    app.mount(f"{DOCS_PATH}/static/vendor", StaticFiles(directory=VENDOR_DIR), name="docs-vendor")
    app.mount(f"{DOCS_PATH}/static/own", StaticFiles(directory=OWN_DIR), name="docs-own")
    static = f"{DOCS_PATH}/static"

    @app.get(DOCS_PATH, include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return _page(
            f"{title}: API",
            f"<link rel='stylesheet' href='{static}/vendor/swagger-ui.css'>",
            f"<body data-openapi-url='{escape(openapi_url)}'><div id='swagger-ui'></div>"
            f"<script src='{static}/vendor/swagger-ui-bundle.js'></script>"
            f"<script src='{static}/own/swagger-init.js'></script></body>",
        )

    @app.get(f"{static}/redoc.js", include_in_schema=False)
    def redoc_js() -> Response:
        return Response(
            redoc_script(),
            media_type="text/javascript",
            headers={"Cache-Control": "public, max-age=3600"},
        )

    @app.get(f"{DOCS_PATH}/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return _page(
            f"{title}: API reference",
            "",
            f"<body><redoc spec-url='{escape(openapi_url)}'></redoc>"
            f"<script src='{static}/redoc.js'></script></body>",
        )
