"""Out-of-range ids are a 404 or a 422 naming the field on every route and both databases.

Issue 16: ids >= 2**63 (SQLite: the driver's OverflowError) or >= 2**31 (PostgreSQL's
INTEGER) gave a 500 with a traceback on 13 routes, anonymous included. Every route with an
``{..._id}`` path parameter, the query and body fields named ``*_id``, each found by walking
the app's OpenAPI schema (a new route is covered without editing this file), get negative,
zero, 2**31, 2**63 and 2**64, and the largest valid id (2**31 - 1, which must reach the
database and come back 404), anonymous and with tokens.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import pytest

from backend.db import MAX_ID
from backend.main import create_app
from backend.settings import Settings

OUT_OF_RANGE = (-1, 0, 2**31, 2**63, 2**64)
ROLES = ("anonymous", "staff_own", "admin")
# Statuses a request with a bad id may get: the id is checked after who is asking.
ALLOWED = {"anonymous": {401, 404, 422}, "staff_own": {403, 404, 422}, "admin": {404, 422}}
FILLERS = {"name": "model.glb", "part": "canvas/1"}  # the other path parameters


def _openapi() -> dict:
    """The app's OpenAPI schema (at collection time: the cases are parameters)."""
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(
            _env_file=None,
            environment="test",
            data_dir=Path(tmp),
            secret_key="ids-test-secret-" + "x" * 40,
            frontend_dist=Path(tmp) / "no-frontend",
        )
        app = create_app(settings)  # connects to nothing until a request comes
        with warnings.catch_warnings():
            # GET+HEAD routes share an operation id; FastAPI warns, the schema is complete.
            warnings.filterwarnings("ignore", "Duplicate Operation ID", category=UserWarning)
            schema = app.openapi()
        app.state.engine.dispose()
    return schema


SCHEMA = _openapi()


def _is_id(name: str, schema: dict) -> bool:
    # Upload ids are UUIDs (strings without digits-only refs); tablet refs are id or P-number.
    return name.endswith("_id") and (
        schema.get("type") == "integer"
        or any(digits in schema.get("pattern", "") for digits in ("\\d{1,", "[0-9]{1,"))
    )


def _body_schema(operation: dict) -> dict:
    content = operation.get("requestBody", {}).get("content", {})
    ref = content.get("application/json", {}).get("schema", {}).get("$ref")
    return SCHEMA["components"]["schemas"][ref.rsplit("/", 1)[1]] if ref else {}


def _body_id_fields(operation: dict) -> list[str]:
    props = _body_schema(operation).get("properties", {})
    out = []
    for name, prop in props.items():
        for option in prop.get("anyOf", [prop]):
            if _is_id(name, option):
                out.append(name)
                break
    return out


def _cases() -> list[tuple[str, str, str, str]]:
    """(method, path template, where the id is: path/query/body, field name)."""
    cases = []
    for path, operations in SCHEMA["paths"].items():
        for method, operation in operations.items():
            for param in operation.get("parameters", []):
                if param["in"] in ("path", "query") and _is_id(param["name"], param["schema"]):
                    cases.append((method.upper(), path, param["in"], param["name"]))
            for name in _body_id_fields(operation):
                cases.append((method.upper(), path, "body", name))
    return cases


CASES = _cases()

# A valid body per route that has one, so that the id is the only thing wrong (a route that
# gains a body or a new id field without an entry here fails test_every_body_is_known).
BODIES = {
    "PATCH /api/v1/users/{user_id}": {"is_active": True},
    "POST /api/v1/users": {"email": "new-user@example.org", "role": "staff"},
    "PATCH /api/v1/tablets/{tablet_id}": {"notes": "checked"},
    "POST /api/v1/tablets": {"designation": "New tablet"},
    "POST /api/v1/uploads": {"filename": "scan.zip", "size_bytes": 10},
    "PATCH /api/v1/institutions/{institution_id}": {"attribution": "A museum"},
    "PATCH /api/v1/models/{model_id}": {"attribution": "A museum"},
    "POST /api/v1/models/{model_id}/annotations": {
        "reference": "o 1 1",
        "polygon_mm": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    },
    "PATCH /api/v1/annotations/{annotation_id}": {"comment": "checked"},
}


def test_the_walk_finds_the_routes_with_ids():
    found = {(m, p, where, name) for m, p, where, name in CASES}
    for expected in [
        ("GET", "/api/v1/tablets/{tablet_id}", "path", "tablet_id"),
        ("GET", "/api/v1/models/{model_id}/assets/{name}", "path", "model_id"),
        ("DELETE", "/api/v1/tokens/{token_id}", "path", "token_id"),
        ("GET", "/api/v1/models", "query", "tablet_id"),
        ("POST", "/api/v1/uploads", "body", "tablet_id"),
        ("POST", "/api/v1/users", "body", "institution_id"),
    ]:
        assert expected in found
    assert not any(name == "upload_id" for *_, name in CASES)  # UUIDs, not integers


def test_every_body_is_known():
    needs_body = {
        f"{m.upper()} {p}"
        for p, ops in SCHEMA["paths"].items()
        for m, op in ops.items()
        if "application/json" in op.get("requestBody", {}).get("content", {})
        and any(f"{m.upper()} {p}" == f"{cm} {cp}" for cm, cp, *_ in CASES)
    }
    assert needs_body <= BODIES.keys(), sorted(needs_body - BODIES.keys())


def _request(method: str, path: str, where: str, name: str, value: int, world) -> dict:
    params = {
        p: FILLERS.get(p, world.public_a) for p in _path_params(path) if p != name
    }  # an existing tablet where another id is needed
    if where == "path":
        params[name] = value
    body = BODIES.get(f"{method} {path}")
    if body is not None:
        body = dict(body)
        if where == "body":
            body[name] = value
    return {
        "method": method,
        "url": path.format(**params),
        "params": {name: value} if where == "query" else None,
        "json": body,
    }


def _path_params(path: str) -> list[str]:
    return [part.split("}")[0] for part in path.split("{")[1:]]


@pytest.mark.parametrize(
    ("method", "path", "where", "name"),
    CASES,
    ids=[f"{m} {p} {w}.{n}" for m, p, w, n in CASES],
)
def test_out_of_range_ids_are_404_or_422(client, world, method, path, where, name):
    problems = []
    for role in ROLES:
        for value in (*OUT_OF_RANGE, MAX_ID):
            request = _request(method, path, where, name, value, world)
            client.cookies.clear()
            response = client.request(**request, headers=world.headers(role))
            status = response.status_code
            label = f"{role}, {where}.{name}={value}: {status} {response.text[:160]}"
            if status not in ALLOWED[role]:
                problems.append(label)
                continue
            if method == "HEAD":
                continue  # no body to check
            body = response.json()
            if set(body) - {"detail", "where", "problems"} or not isinstance(
                body.get("detail"), str
            ):
                problems.append(f"{label}: not the standard error body")
            elif status == 422 and value != MAX_ID and body["where"] != f"{where}.{name}":
                # The message names the culprit (path.x / query.x / body.x).
                problems.append(f"{label}: where should be {where}.{name}")
    assert not problems, "\n".join(problems)


def test_the_largest_id_reaches_the_database(client, world):
    """2**31 - 1 is valid: a 404 (nothing there), not a 422 and not an overflow."""
    for path in ("/api/v1/scans/{}", "/api/v1/models/{}", "/api/v1/tablets/{}"):
        response = client.get(path.format(MAX_ID), headers=world.headers("admin"))
        assert response.status_code == 404, (path, response.text)
    response = client.get(f"/api/v1/tablets/{MAX_ID + 1}", headers=world.headers("admin"))
    assert response.status_code == 404  # a tablet ref of digits: no such record
