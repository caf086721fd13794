"""Every route × every role gets the status the permission matrix states.

The matrix lives in permission_matrix.py; a route without a row fails
``test_every_route_has_a_row``.
"""

from __future__ import annotations

import warnings

import permission_matrix  # tests/backend is on pythonpath
from fastapi.testclient import TestClient

MATRIX, ROLES = permission_matrix.MATRIX, permission_matrix.ROLES


def app_routes(app) -> set[str]:
    """'METHOD /path' of every route in the OpenAPI schema (what clients can call)."""
    with warnings.catch_warnings():
        # GET+HEAD routes share an operation id; FastAPI warns, the schema is still complete.
        warnings.filterwarnings("ignore", message="Duplicate Operation ID", category=UserWarning)
        paths = app.openapi()["paths"]
    return {f"{method.upper()} {path}" for path, methods in paths.items() for method in methods}


def test_every_route_has_a_row(sqlite_app):
    missing = sorted(app_routes(sqlite_app) - MATRIX.keys())
    assert not missing, f"routes without a row in tests/backend/permission_matrix.py: {missing}"


def test_matrix_rows_name_every_role():
    for route, cases in MATRIX.items():
        assert cases, route
        for case in cases:
            assert set(case.expect) == set(ROLES), (route, case.label)


def _call(client: TestClient, world, route: str, case, role: str):
    method, template = route.split(" ", 1)
    path = template.format(**case.params(world, role))
    headers = dict(world.headers(role))
    headers.update(case.headers(world, role) or {})
    client.cookies.clear()
    return client.request(
        method,
        path,
        headers=headers,
        json=case.json(world, role),
        params=case.query(world, role),
        content=case.content(world, role),
    )


def test_permission_matrix(app, world):
    """One test for the whole matrix, listing every mismatch (not just the first)."""
    routes = app_routes(app)
    mismatches = []
    with TestClient(app, raise_server_exceptions=False) as client:
        for route, cases in MATRIX.items():
            if route not in routes:
                mismatches.append(f"{route}: in the matrix but not an app route")
                continue
            for case in cases:
                for role in ROLES:
                    response = _call(client, world, route, case, role)
                    if response.status_code != case.expect[role]:
                        mismatches.append(
                            f"{route} [{case.label}] as {role}: got {response.status_code}, "
                            f"expected {case.expect[role]} ({response.text[:120]})"
                        )
    assert not mismatches, "\n".join(mismatches)
