"""The permission matrix with a replayed session cookie: after logout, the old cookie of every
signed-in role gets exactly what an anonymous visitor gets, on every GET route."""

from __future__ import annotations

import permission_matrix  # tests/backend is on pythonpath
from fastapi.testclient import TestClient

MATRIX, PASSWORD = permission_matrix.MATRIX, permission_matrix.PASSWORD
COOKIE = "hammurabi_session"


def _call_with_cookie(client: TestClient, world, route: str, case, role: str, cookie: str):
    method, template = route.split(" ", 1)
    path = template.format(**case.params(world, role))
    client.cookies.clear()
    client.cookies.set(COOKIE, cookie)
    return client.request(
        method, path, headers=case.headers(world, role) or {}, params=case.query(world, role)
    )


def _signed_in_then_out(client: TestClient, world, role: str) -> str:
    """A cookie taken while signed in (the stolen copy), after the browser logged out."""
    client.cookies.clear()
    login = client.post(
        "/api/v1/auth/login", json={"email": world.emails[role], "password": PASSWORD}
    )
    assert login.status_code == 200, login.text
    stolen = login.cookies[COOKIE]
    assert client.post("/api/v1/auth/logout").status_code == 204
    return stolen


def test_replayed_cookie_after_logout_is_anonymous_on_every_get_route(app, world):
    mismatches = []
    with TestClient(app, raise_server_exceptions=False) as client:
        for role in ("reader", "staff_own", "admin"):
            stolen = _signed_in_then_out(client, world, role)
            for route, cases in MATRIX.items():
                if not route.startswith("GET "):
                    continue
                for case in cases:
                    response = _call_with_cookie(client, world, route, case, role, stolen)
                    if response.status_code != case.expect["anonymous"]:
                        mismatches.append(
                            f"{route} [{case.label}] with {role}'s old cookie: got "
                            f"{response.status_code}, anonymous gets {case.expect['anonymous']}"
                        )
    assert not mismatches, "\n".join(mismatches)


def test_a_live_cookie_gets_what_the_role_gets(app, world):
    """The control: before logout the same cookie is the role (else the replay test proves
    nothing)."""
    with TestClient(app, raise_server_exceptions=False) as client:
        login = client.post(
            "/api/v1/auth/login", json={"email": world.emails["admin"], "password": PASSWORD}
        )
        cookie = login.cookies[COOKIE]
        case = MATRIX["GET /api/v1/users"][0]
        response = _call_with_cookie(client, world, "GET /api/v1/users", case, "admin", cookie)
        assert response.status_code == case.expect["admin"] == 200
