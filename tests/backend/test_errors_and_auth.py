"""Errors as {detail, where}; CORS for reads; sessions and API tokens."""

from __future__ import annotations

import hashlib

from fastapi.testclient import TestClient
from sqlalchemy import select

from backend.main import create_app
from backend.tables import ApiToken

PASSWORD = "correct horse battery staple"  # conftest.PASSWORD


def test_not_found_and_unauthorized_shapes(client):
    response = client.get("/api/v1/tablets/999999")
    assert response.status_code == 404
    assert response.json() == {"detail": "tablet 999999 not found", "where": "tablet_id"}
    response = client.get("/api/v1/auth/me")
    assert response.status_code == 401
    assert set(response.json()) == {"detail", "where"}
    assert client.get("/api/v1/nothing-here").json() == {"detail": "Not Found", "where": None}


def test_validation_error_names_the_field(client, world):
    response = client.post(
        "/api/v1/tablets",
        json={"designation": "x", "height_mm": "tall"},
        headers=world.headers("staff_own"),
    )
    assert response.status_code == 422
    body = response.json()
    assert body["where"] == "body.height_mm"
    assert body["problems"][0]["where"] == "body.height_mm"
    assert "height_mm" in body["detail"]


def test_server_error_has_no_traceback(settings):
    app = create_app(settings)

    @app.get("/api/v1/boom")
    def boom():
        raise RuntimeError("secret internals")

    with TestClient(app, raise_server_exceptions=False) as client:
        response = client.get("/api/v1/boom")
    app.state.engine.dispose()
    assert response.status_code == 500
    assert response.json() == {"detail": "internal server error", "where": None}
    assert "secret internals" not in response.text


def test_cors_allows_reads_from_anywhere(client):
    response = client.get("/api/v1/tablets", headers={"Origin": "https://elsewhere.example"})
    assert response.headers["access-control-allow-origin"] == "*"
    preflight = client.options(
        "/api/v1/tablets",
        headers={"Origin": "https://elsewhere.example", "Access-Control-Request-Method": "POST"},
    )
    assert preflight.status_code == 400  # writes are not allowed cross-origin


def test_login_cookie_session(client, world):
    response = client.post(
        "/api/v1/auth/login", json={"email": world.emails["staff_own"], "password": PASSWORD}
    )
    assert response.status_code == 200
    cookie = response.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=lax" in cookie and "hammurabi_session=" in cookie
    assert client.get("/api/v1/auth/me").json()["email"] == world.emails["staff_own"]
    # the session sees the institution's private records
    assert client.get(f"/api/v1/tablets/{world.private_a}").status_code == 200
    assert client.post("/api/v1/auth/logout").status_code == 204
    assert client.get("/api/v1/auth/me").status_code == 401


def test_wrong_password_and_tampered_cookie(client, world):
    response = client.post(
        "/api/v1/auth/login", json={"email": world.emails["admin"], "password": "wrong"}
    )
    assert response.status_code == 401
    assert "set-cookie" not in response.headers
    client.cookies.set("hammurabi_session", "eyJ1aWQiOjF9.forged.signature")
    assert client.get("/api/v1/auth/me").status_code == 401


def test_tokens_are_hashed_shown_once_and_revocable(client, world):
    headers = world.headers("reader")
    created = client.post("/api/v1/tokens", json={"name": "archive"}, headers=headers)
    assert created.status_code == 201
    secret = created.json()["secret"]
    listed = client.get("/api/v1/tokens", headers=headers).json()
    assert all("secret" not in t for t in listed)
    assert created.json()["prefix"] in secret and len(created.json()["prefix"]) < len(secret)
    with world.session() as session:
        stored = session.scalar(select(ApiToken).where(ApiToken.id == created.json()["id"]))
        assert stored.token_hash == hashlib.sha256(secret.encode()).hexdigest()

    new_headers = {"Authorization": f"Bearer {secret}"}
    assert client.get("/api/v1/auth/me", headers=new_headers).status_code == 200
    with world.session() as session:
        assert session.get(ApiToken, created.json()["id"]).last_used_at is not None
    revoked = client.delete(f"/api/v1/tokens/{created.json()['id']}", headers=headers)
    assert revoked.json()["revoked_at"] is not None
    response = client.get("/api/v1/auth/me", headers=new_headers)
    assert response.status_code == 401
    assert response.json()["detail"] == "invalid or revoked API token"


def test_malformed_authorization_is_401(client):
    response = client.get("/api/v1/tablets", headers={"Authorization": "Basic abc"})
    assert response.status_code == 401


def test_tablet_crud_and_stable_urls(client, world):
    headers = world.headers("staff_own")
    created = client.post(
        "/api/v1/tablets",
        json={"designation": "BM 1", "p_number": "P123456", "height_mm": 45.5},
        headers=headers,
    )
    assert created.status_code == 201
    body = created.json()
    assert body["institution"] == "Museum A" and body["is_public"] is False
    assert client.get(body["url"], headers=headers).json()["p_number"] == "P123456"
    assert client.get("/api/v1/tablets/P123456", headers=headers).json()["id"] == body["id"]
    duplicate = client.post(
        "/api/v1/tablets", json={"designation": "BM 2", "p_number": "P123456"}, headers=headers
    )
    assert duplicate.status_code == 409 and duplicate.json()["where"] == "p_number"
    patched = client.patch(
        body["url"], json={"is_public": True, "notes": "fine", "height_mm": None}, headers=headers
    )
    assert patched.json()["is_public"] is True and patched.json()["height_mm"] is None
    assert client.get(body["url"]).status_code == 200  # public now
    refused = client.patch(body["url"], json={"designation": None}, headers=headers)
    assert refused.status_code == 422 and refused.json()["where"] == "body.designation"
    assert client.delete(body["url"], headers=headers).status_code == 204
    assert client.get(body["url"], headers=headers).status_code == 404


def test_admin_manages_users(client, world):
    headers = world.headers("admin")
    created = client.post(
        "/api/v1/users",
        json={"email": "New@Example.org", "role": "staff", "institution_id": world.institution_b,
              "password": "long enough"},
        headers=headers,
    )  # fmt: skip
    assert created.status_code == 201
    assert (created.json()["email"], created.json()["institution"]) == (
        "new@example.org",
        "Museum B",
    )
    staff_without_home = client.post(
        "/api/v1/users", json={"email": "x@example.org", "role": "staff"}, headers=headers
    )
    assert staff_without_home.status_code == 422
    assert staff_without_home.json()["where"] == "body.institution_id"
    deactivated = client.patch(
        f"/api/v1/users/{created.json()['id']}", json={"is_active": False}, headers=headers
    )
    assert deactivated.json()["is_active"] is False
    login = client.post(
        "/api/v1/auth/login", json={"email": "new@example.org", "password": "long enough"}
    )
    assert login.status_code == 401
