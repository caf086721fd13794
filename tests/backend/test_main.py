"""create_app: the built frontend at /, the API under /api/v1, OpenAPI at /docs."""

from __future__ import annotations

from fastapi.testclient import TestClient

from backend.main import create_app


def test_frontend_is_served_next_to_the_api(tmp_path, settings):
    dist = tmp_path / "dist"
    dist.mkdir()
    (dist / "index.html").write_text("<!doctype html><title>library</title>")
    (dist / "tablet.html").write_text("<!doctype html><title>tablet</title>")
    app = create_app(settings.model_copy(update={"frontend_dist": dist}))
    with TestClient(app) as client:
        assert "<title>library</title>" in client.get("/").text
        assert "<title>tablet</title>" in client.get("/tablet.html").text
        assert client.get("/api/v1/health").json() == {"status": "ok"}
        assert client.get("/docs").status_code == 200
        assert client.get("/api/v1/openapi.json").status_code == 200
        assert client.get("/missing.js").status_code == 404
    app.state.engine.dispose()


def test_no_frontend_no_mount(client):
    assert client.get("/").status_code == 404
    assert client.get("/").json()["where"] is None
