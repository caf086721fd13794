"""Authentication before validation: an anonymous write is a 401 whatever its body.

A 422 first told an anonymous caller about the body's shape before telling it that it may
not write at all (``PATCH /models/1`` with a bad body answered 422). Every write route of
the OpenAPI document that declares a security scheme is tried, anonymous, with a body of
the wrong shape and with a body that is not JSON at all.
"""

from __future__ import annotations

import re

import pytest

from backend.tables import Annotation

WRITE_METHODS = ("post", "put", "patch", "delete")
BAD_BODIES = {
    "wrong shape": {"content": b'["not", "an", "object"]'},
    "not JSON": {"content": b"{not json"},
    "wrong types": {"content": b'{"designation": 5, "licence": [], "role": 7, "name": {}}'},
}


def _secured_write_routes(app) -> list[tuple[str, str]]:
    routes = []
    for path, item in app.openapi()["paths"].items():
        for method, operation in item.items():
            if method in WRITE_METHODS and operation.get("security"):
                routes.append((method.upper(), path))
    return routes


def test_the_secured_write_routes_are_found(sqlite_app):
    routes = _secured_write_routes(sqlite_app)
    assert ("PATCH", "/api/v1/models/{model_id}") in routes
    assert ("POST", "/api/v1/tablets") in routes
    # Logging in is the one write an anonymous caller makes.
    assert all(path != "/api/v1/auth/login" for _, path in routes)
    assert len(routes) >= 15


@pytest.mark.parametrize("body", list(BAD_BODIES))
def test_anonymous_writes_are_401_whatever_the_body(client, world, body):
    # Resources that exist and are public, so that a 404 cannot hide the answer.
    model_id = world.new_model(world.public_a)
    with world.session() as session:
        annotation = Annotation(
            model_id=model_id, tablet_id=world.public_a, reference="o 1 1", polygon_mm=[]
        )
        session.add(annotation)
        session.flush()
        annotation_id = annotation.id
    wrong = []
    for method, template in _secured_write_routes(client.app):
        path = re.sub(r"\{model_id\}", str(model_id), template)
        path = re.sub(r"\{tablet_id\}", str(world.public_a), path)
        path = re.sub(r"\{annotation_id\}", str(annotation_id), path)
        path = re.sub(r"\{[a-z_]+\}", "1", path)
        response = client.request(
            method, path, headers={"Content-Type": "application/json"}, **BAD_BODIES[body]
        )
        if response.status_code != 401:
            wrong.append((method, template, response.status_code, response.text[:80]))
        else:
            assert response.headers.get("www-authenticate") == "Bearer"
            assert set(response.json()) == {"detail", "where"}
    assert wrong == []


def test_a_signed_in_caller_still_learns_what_is_wrong_with_the_body(client, world):
    model_id = world.new_model(world.public_a)
    response = client.patch(
        f"/api/v1/models/{model_id}",
        content=b"{not json",
        headers={**world.headers("staff_own"), "Content-Type": "application/json"},
    )
    assert response.status_code == 422
