"""Session cookies are revocable (issue 16, item 6): after logout, a password change or the
account being disabled, a copy of the old cookie is refused (401), on SQLite and PostgreSQL."""

from __future__ import annotations

from fastapi.testclient import TestClient

from backend.security import SessionSigner
from tests.backend.conftest import PASSWORD

ME = "/api/v1/auth/me"
COOKIE = "hammurabi_session"


def _login(client: TestClient, email: str, password: str = PASSWORD) -> str:
    response = client.post("/api/v1/auth/login", json={"email": email, "password": password})
    assert response.status_code == 200, response.text
    return response.cookies[COOKIE]


def _me_with(app, cookie: str) -> int:
    # A fresh client: the attacker's copy of the cookie, not the browser's jar.
    with TestClient(app, cookies={COOKIE: cookie}) as other:
        return other.get(ME).status_code


def test_cookie_replay_after_logout_is_refused(app, client, world):
    stolen = _login(client, world.emails["reader"])
    assert _me_with(app, stolen) == 200
    assert client.post("/api/v1/auth/logout").status_code == 204
    assert _me_with(app, stolen) == 401
    # logging in again gives a working session
    assert _me_with(app, _login(client, world.emails["reader"])) == 200
    assert _me_with(app, stolen) == 401


def test_cookie_replay_after_password_change_is_refused(app, client, world):
    stolen = _login(client, world.emails["staff_own"])
    response = client.patch(
        f"/api/v1/users/{world.users['staff_own']}",
        json={"password": "a new long password"},
        headers=world.headers("admin"),
    )
    assert response.status_code == 200, response.text
    assert _me_with(app, stolen) == 401
    assert _me_with(app, _login(client, world.emails["staff_own"], "a new long password")) == 200


def test_cookie_replay_after_disable_is_refused_even_when_enabled_again(app, client, world):
    stolen = _login(client, world.emails["staff_own"])
    url = f"/api/v1/users/{world.users['staff_own']}"
    admin = world.headers("admin")
    assert client.patch(url, json={"is_active": False}, headers=admin).status_code == 200
    assert _me_with(app, stolen) == 401
    assert client.patch(url, json={"is_active": True}, headers=admin).status_code == 200
    assert _me_with(app, stolen) == 401


def test_other_changes_keep_the_session(app, client, world):
    cookie = _login(client, world.emails["staff_own"])
    url = f"/api/v1/users/{world.users['staff_own']}"
    response = client.patch(url, json={"role": "staff"}, headers=world.headers("admin"))
    assert response.status_code == 200
    assert _me_with(app, cookie) == 200


def test_cookie_without_a_session_version_is_refused(app, world):
    # signed with the right key, but in the format of before session versions
    signer = SessionSigner(app.state.settings.signing_secret, max_age_s=3600)
    legacy = signer._serializer.dumps({"uid": world.users["admin"]})
    assert _me_with(app, legacy) == 401
    assert _me_with(app, signer.dumps(world.users["admin"], 0)) == 200
    assert _me_with(app, signer.dumps(world.users["admin"], 1)) == 401


def test_own_password_change_ends_other_sessions_and_keeps_this_one(app, client, world):
    email = world.emails["reader"]
    stolen = _login(client, email)
    response = client.post(
        "/api/v1/auth/password",
        json={"current_password": PASSWORD, "new_password": "a brand new password"},
    )
    assert response.status_code == 204, response.text
    fresh = response.cookies[COOKIE]
    assert _me_with(app, stolen) == 401
    assert _me_with(app, fresh) == 200
    with TestClient(app) as other:
        assert _login(other, email, "a brand new password")


def test_own_password_change_needs_the_current_password(app, client, world):
    cookie = _login(client, world.emails["reader"])
    response = client.post(
        "/api/v1/auth/password",
        json={"current_password": "not it", "new_password": "a brand new password"},
    )
    assert response.status_code == 403
    assert response.json()["where"] == "body.current_password"
    assert _me_with(app, cookie) == 200  # nothing changed
    token = client.post(
        "/api/v1/auth/password",
        json={"current_password": "not it", "new_password": "a brand new password"},
        headers=world.headers("staff_own"),
    )
    assert token.status_code == 403  # the same through an API token


SESSION = "/api/v1/auth/session"


def test_session_is_null_for_anonymous_and_revoked_cookies_and_the_user_when_signed_in(
    app, client, world
):
    assert client.get(SESSION).json() == {"user": None}
    cookie = _login(client, world.emails["reader"])
    body = client.get(SESSION).json()
    assert body["user"]["email"] == world.emails["reader"]
    assert body["user"]["role"] == "reader"
    assert client.post("/api/v1/auth/logout").status_code == 204
    with TestClient(app, cookies={COOKIE: cookie}) as other:  # the old cookie, replayed
        response = other.get(SESSION)
    assert response.status_code == 200
    assert response.json() == {"user": None}
    with TestClient(app, cookies={COOKIE: "forged.value"}) as other:
        assert other.get(SESSION).json() == {"user": None}
