"""Request bodies are capped (backend.body_limit): an anonymous 400 MB POST used to be read and
parsed in full before its 401. Upload chunks, streamed to disk, are exempt."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from backend.main import create_app
from backend.tables import Tablet
from tests.backend.conftest import build_world, make_settings

API = "/api/v1"
CAP_BYTES = 4096


@pytest.fixture
def capped(sqlite_url, tmp_path, password_hash):
    app = create_app(make_settings(sqlite_url, tmp_path, request_max_body_bytes=CAP_BYTES))
    world = build_world(app.state.sessionmaker, password_hash, app.state.settings)
    with TestClient(app) as client:
        yield client, world, app
    app.state.engine.dispose()


def _tablet_count(app) -> int:
    with app.state.sessionmaker() as session:
        return session.scalar(select(func.count()).select_from(Tablet))


def _body(n_bytes: int) -> bytes:
    head, tail = b'{"designation": "big", "notes": "', b'"}'
    return head + b"a" * (n_bytes - len(head) - len(tail)) + tail


@pytest.mark.parametrize("role", ["anonymous", "admin"])
def test_declared_body_over_the_cap_is_refused_before_the_route(capped, role):
    client, world, app = capped
    before = _tablet_count(app)
    body = _body(CAP_BYTES + 1)
    r = client.post(
        f"{API}/tablets",
        content=body,
        headers=world.headers(role) | {"Content-Type": "application/json"},
    )
    assert r.status_code == 413, r.text
    assert r.json()["where"] == "body"
    assert str(CAP_BYTES) in r.json()["detail"]
    assert _tablet_count(app) == before


def test_chunked_body_over_the_cap_is_refused(capped):
    client, world, app = capped
    before = _tablet_count(app)
    body = _body(3 * CAP_BYTES)

    def pieces():  # no Content-Length: chunked transfer
        for i in range(0, len(body), 1000):
            yield body[i : i + 1000]

    r = client.post(
        f"{API}/tablets",
        content=pieces(),
        headers=world.headers("admin") | {"Content-Type": "application/json"},
    )
    assert r.status_code == 413, r.text
    assert set(r.json()) >= {"detail", "where"}
    assert _tablet_count(app) == before


def test_body_under_the_cap_is_served(capped):
    client, world, app = capped
    r = client.post(
        f"{API}/tablets",
        content=_body(CAP_BYTES - 10),
        headers=world.headers("admin") | {"Content-Type": "application/json"},
    )
    assert r.status_code == 201, r.text


def test_upload_chunks_are_not_capped(capped):
    client, world, _app = capped
    data = bytes(range(256)) * (3 * CAP_BYTES // 256)
    body = {"tablet_id": world.private_a, "filename": "scan.zip", "size_bytes": len(data)}
    upload = client.post(f"{API}/uploads", json=body, headers=world.headers("staff_own"))
    assert upload.status_code == 201, upload.text
    r = client.put(
        f"{API}/uploads/{upload.json()['id']}/chunks",
        params={"offset": 0},
        content=data,
        headers=world.headers("staff_own") | {"Content-Type": "application/octet-stream"},
    )
    assert r.status_code == 200, r.text
    assert r.json()["received_bytes"] == len(data)
