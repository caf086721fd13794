"""Security headers on every response (issue 16, item 8): API, errors, the frontend's pages
and assets, the OpenAPI page; HSTS only over TLS or with an https public URL."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from backend.headers import CSP, DOCS_CSP
from backend.main import create_app
from tests.backend.conftest import make_settings

COMMON = {
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "same-origin",
}


@pytest.fixture
def site(sqlite_url, tmp_path):
    dist = tmp_path / "dist"
    (dist / "assets").mkdir(parents=True)
    (dist / "index.html").write_text("<!doctype html><title>library</title>")
    (dist / "assets" / "app.js").write_text("export {};")
    app = create_app(make_settings(sqlite_url, tmp_path, frontend_dist=dist))
    yield app
    app.state.engine.dispose()


def _check(response, csp=CSP):
    for name, value in COMMON.items():
        assert response.headers.get(name) == value, (name, response.request.url)
    assert response.headers["content-security-policy"] == csp
    assert "frame-ancestors 'none'" in csp


@pytest.mark.parametrize(
    "path",
    [
        "/api/v1/health",
        "/api/v1/tablets",
        "/api/v1/tablets/999999",  # 404
        "/api/v1/auth/me",  # 401
        "/api/v1/tablets?page_size=-1",  # 422
        "/",
        "/assets/app.js",
        "/missing-page",
    ],
)
def test_every_response_has_the_headers(site, path):
    with TestClient(site) as client:
        response = client.get(path)
    _check(response)
    assert "strict-transport-security" not in response.headers  # plain http


def test_cors_preflight_has_them_too(site):
    with TestClient(site) as client:
        response = client.options(
            "/api/v1/tablets",
            headers={"Origin": "https://other.example", "Access-Control-Request-Method": "GET"},
        )
    assert response.status_code == 200
    _check(response)


def test_openapi_page_gets_its_own_policy(site):
    with TestClient(site) as client:
        response = client.get("/docs")
    assert response.status_code == 200
    _check(response, DOCS_CSP)


def test_hsts_only_over_tls(site):
    with TestClient(site, base_url="https://library.example") as client:
        response = client.get("/api/v1/health")
    assert response.headers["strict-transport-security"].startswith("max-age=31536000")


def test_csp_lets_the_viewer_work():
    policy = dict(part.split(" ", 1) for part in CSP.split("; "))
    # no inline script, no eval; WebAssembly may compile (the tiles' meshopt decoder)
    assert policy["script-src"] == "'self' 'wasm-unsafe-eval'"
    assert "unsafe-eval'" not in policy["script-src"].replace("'wasm-unsafe-eval'", "")
    for needed in ("blob:", "data:"):  # GLTFLoader's embedded textures
        assert needed in policy["img-src"] and needed in policy["connect-src"]
