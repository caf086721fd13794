"""The API contract: what OpenAPI documents is what is sent (error bodies, timestamps),
and the documentation pages need nothing from the internet."""

from __future__ import annotations

import re
from datetime import datetime

import jsonschema_rs
import pytest

API = "/api/v1"


def _schema_of(openapi: dict, name: str) -> dict:
    # The component with the document's components alongside, so its $refs resolve.
    return {**openapi["components"]["schemas"][name], "components": openapi["components"]}


def test_the_422_body_is_the_documented_one(client, world):
    openapi = client.get(f"{API}/openapi.json").json()
    create = openapi["paths"][f"{API}/tablets"]["post"]["responses"]["422"]
    ref = create["content"]["application/json"]["schema"]["$ref"]
    assert ref == "#/components/schemas/HTTPValidationError"
    assert "ValidationError" not in openapi["components"]["schemas"]  # FastAPI's, unused

    response = client.post(
        f"{API}/tablets", json={"designation": "", "height_mm": -1}, headers=world.headers("admin")
    )
    assert response.status_code == 422
    body = response.json()
    jsonschema_rs.validate(_schema_of(openapi, "HTTPValidationError"), body)
    assert {p["where"] for p in body["problems"]} == {"body.designation", "body.height_mm"}
    # FastAPI's own shape must fail the documented schema: the test can tell them apart.
    fastapi_body = {"detail": [{"loc": ["body", "designation"], "msg": "x", "type": "y"}]}
    assert not jsonschema_rs.validator_for(_schema_of(openapi, "HTTPValidationError")).is_valid(
        fastapi_body
    )


@pytest.mark.parametrize("db", ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def test_timestamps_are_utc_with_an_offset_from_every_database(
    db, sqlite_url, pg_database, tmp_path, password_hash
):
    from fastapi.testclient import TestClient

    from backend.main import create_app
    from tests.backend.conftest import _pg_truncated, build_world, make_settings

    url = sqlite_url if db == "sqlite" else _pg_truncated(pg_database)
    app = create_app(make_settings(url, tmp_path))
    world = build_world(app.state.sessionmaker, password_hash, app.state.settings)
    try:
        with TestClient(app) as client:
            created = client.post(
                f"{API}/tablets", json={"designation": "T 1"}, headers=world.headers("admin")
            ).json()
            read = client.get(created["url"], headers=world.headers("admin")).json()
            listed = client.get(f"{API}/institutions").json()
    finally:
        app.state.engine.dispose()
    for stamp in (created["created_at"], read["created_at"], read["updated_at"]):
        assert re.search(r"(Z|\+00:00)$", stamp), stamp
    assert datetime.fromisoformat(read["created_at"]) == datetime.fromisoformat(
        created["created_at"]
    )
    assert all(re.search(r"(Z|\+00:00)$", i["created_at"]) for i in listed)


def test_docs_pages_load_only_our_own_files(client):
    for path in ("/docs", "/docs/redoc"):
        response = client.get(path)
        assert response.status_code == 200 and response.headers["content-type"].startswith(
            "text/html"
        )
        assets = re.findall(r"(?:src|href)='([^']+)'", response.text)
        assert assets and all(a.startswith("/docs/static/") for a in assets), assets
        assert "<script>" not in response.text  # no inline script: the CSP forbids them
        for asset in assets:
            fetched = client.get(asset)
            assert fetched.status_code == 200 and len(fetched.content) > 100, asset
    assert "cdn" not in client.get("/docs").headers["content-security-policy"]


def test_redoc_loads_its_credit_logo_from_us_not_from_its_cdn(client):
    # The vendored bundle asks cdn.redoc.ly for its sidebar logo: the CSP refused it, a
    # console error on every visit. Our copy names a local image.
    page = client.get("/docs/redoc").text
    script_url = re.search(r"<script src='([^']+)'", page).group(1)
    script = client.get(script_url)
    assert script.status_code == 200
    assert script.headers["content-type"].startswith("text/javascript")
    assert b"cdn.redoc.ly" not in script.content
    assert b"/docs/static/own/redoc-logo.svg" in script.content
    logo = client.get("/docs/static/own/redoc-logo.svg")
    assert logo.status_code == 200 and logo.headers["content-type"].startswith("image/svg+xml")
