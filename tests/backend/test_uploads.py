"""The resumable upload protocol through the API (SQLite; test_uploads_databases.py runs the
main path on PostgreSQL as well)."""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import random
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from backend import uploads as uploads_mod
from backend.api import uploads as api_uploads_mod
from backend.jobs import RECONSTRUCT_TASK, RecordingDispatcher
from backend.main import create_app
from backend.storage import LocalStorage
from backend.storage import local as storage_mod
from backend.tables import Upload
from worker.bundle import write_bundle

API = "/api/v1"


def bundle_bytes(tmp_path: Path, *, scan_id: str | None = "rig-0001", face: str = "obverse"):
    """A small valid bundle ZIP: four photometric frames of 16 x 12 8-bit pixels."""
    scan = {"face": face} | ({"id": scan_id} if scan_id else {})
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": scan,
        "camera": {"width": 16, "height": 12, "pixel_size_um": 50, "bit_depth": 8},
        "source": {"polar_deg": 45},
        "frames": [
            {"file": f"p{i}.png", "kind": "photometric", "azimuth_deg": 90 * i} for i in range(4)
        ],
    }
    rng = np.random.default_rng(7)
    images = {f"p{i}.png": rng.integers(0, 255, (12, 16), dtype=np.uint8) for i in range(4)}
    out = tmp_path / f"bundle-{random.randrange(1 << 30)}.zip"
    return write_bundle(out, manifest, images, as_zip=True).read_bytes()


def invalid_bundle_bytes() -> bytes:
    """A ZIP whose manifest has three independent problems."""
    manifest = {
        "format": "cuneiform-scan",
        "version": 1,
        "scan": {"face": "sideways"},
        "camera": {"width": 16, "height": 12, "pixel_size_um": -1, "bit_depth": 8},
        "source": {"polar_deg": 45},
        "frames": [{"file": "missing.png", "kind": "photometric", "azimuth_deg": 0}],
    }
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("manifest.json", json.dumps(manifest))
    return buffer.getvalue()


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def create(client, world, data: bytes, *, role="staff_own", tablet=None, filename="scan.zip"):
    body = {
        "tablet_id": tablet or world.private_a,
        "filename": filename,
        "size_bytes": len(data),
    }
    return client.post(f"{API}/uploads", json=body, headers=world.headers(role))


def put(client, world, upload_id, offset, chunk, role="staff_own"):
    return client.put(
        f"{API}/uploads/{upload_id}/chunks",
        params={"offset": offset},
        content=chunk,
        headers=world.headers(role) | {"Content-Type": "application/octet-stream"},
    )


def complete(client, world, upload_id, digest, role="staff_own"):
    return client.post(
        f"{API}/uploads/{upload_id}/complete", json={"sha256": digest}, headers=world.headers(role)
    )


def upload_all(client, world, data: bytes, *, chunk=1000, tablet=None):
    response = create(client, world, data, tablet=tablet)
    assert response.status_code == 201, response.text
    upload_id = response.json()["id"]
    for offset in range(0, len(data), chunk):
        assert (
            put(client, world, upload_id, offset, data[offset : offset + chunk]).status_code == 200
        )
    return upload_id, complete(client, world, upload_id, sha(data))


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


@pytest.fixture
def dispatcher(app) -> RecordingDispatcher:
    app.state.dispatcher = RecordingDispatcher()
    return app.state.dispatcher


def test_chunks_in_any_order_repeated_then_complete(client, world, dispatcher, tmp_path, app):
    data = bundle_bytes(tmp_path)
    created = create(client, world, data)
    assert created.status_code == 201
    state = created.json()
    assert state["received_bytes"] == 0 and state["ranges"] == []
    assert state["missing"] == [[0, len(data)]] and state["state"] == "open"
    assert state["chunk_size"] == app.state.settings.upload_chunk_size_bytes
    upload_id = state["id"]

    chunk = 512
    offsets = list(range(0, len(data), chunk))
    random.Random(3).shuffle(offsets)
    half = offsets[: len(offsets) // 2]
    for offset in half + half[:2]:  # repeating chunks is harmless
        assert (
            put(client, world, upload_id, offset, data[offset : offset + chunk]).status_code == 200
        )
    state = client.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own")).json()
    expected = sum(len(data[o : o + chunk]) for o in half)
    assert state["received_bytes"] == expected
    assert sum(hi - lo for lo, hi in state["missing"]) == len(data) - expected

    early = complete(client, world, upload_id, sha(data))
    assert early.status_code == 409 and early.json()["where"] == "ranges"

    for lo, hi in state["missing"]:  # resume: send exactly what the server says is missing
        assert put(client, world, upload_id, lo, data[lo:hi]).status_code == 200
    done = complete(client, world, upload_id, sha(data))
    assert done.status_code == 201, done.text
    scan, job = done.json()["scan"], done.json()["job"]
    assert scan["face"] == "obverse" and scan["scan_uid"] == "rig-0001"
    assert scan["tablet_id"] == world.private_a and scan["size_bytes"] == len(data)
    assert job["state"] == "queued" and job["scan_id"] == scan["id"]
    assert scan["latest_job"]["id"] == job["id"]
    assert dispatcher.sent == [(RECONSTRUCT_TASK, [job["id"]], f"job-{job['id']}-attempt-1")]

    store = LocalStorage(app.state.settings.resolved_storage_dir)
    (key,) = store.list("scans/")
    assert store.read_bytes(key) == data and store.stat(key).etag == sha(data)
    assert list((app.state.settings.data_dir / "uploads").iterdir()) == []  # part file gone
    final = client.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own")).json()
    assert final["state"] == "complete" and final["missing"] == []

    again = complete(client, world, upload_id, sha(data))  # a lost response, asked again
    assert again.status_code == 200 and again.json()["scan"]["id"] == scan["id"]
    assert len(dispatcher.sent) == 1


def test_same_scan_id_twice_is_the_same_scan(client, world, dispatcher, tmp_path, app):
    data = bundle_bytes(tmp_path, scan_id="rig-same")
    _, first = upload_all(client, world, data)
    assert first.status_code == 201
    _, second = upload_all(client, world, data, chunk=1000)
    assert second.status_code == 200
    assert second.json()["scan"]["id"] == first.json()["scan"]["id"]
    assert second.json()["job"]["id"] == first.json()["job"]["id"]
    assert len(dispatcher.sent) == 1
    assert len(LocalStorage(app.state.settings.resolved_storage_dir).list("scans/")) == 1
    scans = client.get(f"{API}/tablets/{world.private_a}/scans", headers=world.headers("admin"))
    assert [s["id"] for s in scans.json()] == [first.json()["scan"]["id"]]

    # Without scan.id every upload is a new scan.
    plain = bundle_bytes(tmp_path, scan_id=None, face="reverse")
    assert upload_all(client, world, plain)[1].status_code == 201
    assert upload_all(client, world, plain)[1].status_code == 201


def test_same_scan_id_on_another_tablet_is_refused(client, world, dispatcher, tmp_path):
    data = bundle_bytes(tmp_path, scan_id="rig-x")
    assert upload_all(client, world, data)[1].status_code == 201
    upload_id, response = upload_all(client, world, data, tablet=world.public_a)
    assert response.status_code == 409 and response.json()["where"] == "manifest.scan.id"


def test_checksum_mismatch_names_the_sha256_and_keeps_nothing(
    client, world, dispatcher, tmp_path, app
):
    data = bundle_bytes(tmp_path)
    upload_id = create(client, world, data).json()["id"]
    corrupted = bytearray(data)
    corrupted[100] ^= 0xFF
    assert put(client, world, upload_id, 0, bytes(corrupted)).status_code == 200
    response = complete(client, world, upload_id, sha(data))
    assert response.status_code == 422
    body = response.json()
    assert body["where"] == "sha256"
    assert sha(bytes(corrupted)) in body["detail"] and sha(data) in body["detail"]
    assert list((app.state.settings.data_dir / "uploads").iterdir()) == []
    assert LocalStorage(app.state.settings.resolved_storage_dir).list() == []
    assert dispatcher.sent == []
    state = client.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own")).json()
    assert state["state"] == "failed"
    assert put(client, world, upload_id, 0, data).status_code == 409


def test_invalid_bundle_lists_every_problem_and_keeps_nothing(client, world, dispatcher, app):
    data = invalid_bundle_bytes()
    upload_id = create(client, world, data).json()["id"]
    assert put(client, world, upload_id, 0, data).status_code == 200
    response = complete(client, world, upload_id, sha(data))
    assert response.status_code == 422
    problems = response.json()["problems"]
    wheres = " ".join(p["where"] for p in problems)
    assert (
        "scan.face" in wheres
        and "pixel_size_um" in wheres
        and "missing.png" in json.dumps(problems)
    )
    assert all(set(p) == {"where", "message"} for p in problems)
    assert str(app.state.settings.data_dir) not in json.dumps(response.json())  # no server paths
    assert list((app.state.settings.data_dir / "uploads").iterdir()) == []
    assert LocalStorage(app.state.settings.resolved_storage_dir).list() == []
    scans = client.get(f"{API}/tablets/{world.private_a}/scans", headers=world.headers("admin"))
    assert scans.json() == [] and dispatcher.sent == []


def test_not_a_zip_is_a_problem_naming_the_file(client, world, dispatcher):
    data = b"this is not a zip file at all"
    upload_id = create(client, world, data, filename="rig.zip").json()["id"]
    put(client, world, upload_id, 0, data)
    response = complete(client, world, upload_id, sha(data))
    assert response.status_code == 422
    assert "rig.zip" in response.json()["problems"][0]["message"]


def test_upload_survives_a_server_restart(client, world, dispatcher, tmp_path, settings):
    data = bundle_bytes(tmp_path)
    upload_id = create(client, world, data).json()["id"]
    half = len(data) // 2
    assert put(client, world, upload_id, 0, data[:half]).status_code == 200

    restarted = create_app(settings)  # same database and data dir, fresh process state
    restarted.state.dispatcher = RecordingDispatcher()
    with TestClient(restarted) as again:
        state = again.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own"))
        assert state.json()["missing"] == [[half, len(data)]]
        assert put(again, world, upload_id, half, data[half:]).status_code == 200
        assert complete(again, world, upload_id, sha(data)).status_code == 201
    restarted.state.engine.dispose()


def test_chunk_past_the_end_is_refused(client, world):
    upload_id = create(client, world, b"x" * 100).json()["id"]
    response = put(client, world, upload_id, 90, b"y" * 20)
    assert response.status_code == 422 and response.json()["where"] == "offset"
    state = client.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own")).json()
    assert state["received_bytes"] == 0
    assert put(client, world, upload_id, -1, b"y").status_code == 422


def test_size_limit_and_filename(client, world, app, settings):
    big = settings.upload_max_bytes + 1
    response = client.post(
        f"{API}/uploads",
        json={"tablet_id": world.private_a, "filename": "a.zip", "size_bytes": big},
        headers=world.headers("staff_own"),
    )
    assert response.status_code == 413 and response.json()["where"] == "size_bytes"
    for filename in ["a.tar", "../a.zip", ""]:
        response = client.post(
            f"{API}/uploads",
            json={"tablet_id": world.private_a, "filename": filename, "size_bytes": 10},
            headers=world.headers("staff_own"),
        )
        assert response.status_code == 422, filename


def test_abandon_an_upload(client, world, app):
    upload_id = create(client, world, b"z" * 50).json()["id"]
    headers = world.headers("staff_own")
    assert client.delete(f"{API}/uploads/{upload_id}", headers=headers).status_code == 204
    assert client.get(f"{API}/uploads/{upload_id}", headers=headers).status_code == 404
    assert list((app.state.settings.data_dir / "uploads").iterdir()) == []


@pytest.mark.parametrize(
    ("role", "tablet", "status"),
    [
        ("anonymous", "private_a", 401),
        ("reader", "public_a", 403),
        ("staff_other", "public_a", 403),
        ("staff_other", "private_a", 404),  # a private record of others is not revealed
        ("staff_own", "private_a", 201),
        ("admin", "private_b", 201),
        ("admin", 999_999, 404),
    ],
)
def test_who_may_upload(client, world, role, tablet, status):
    tablet_id = getattr(world, tablet) if isinstance(tablet, str) else tablet
    response = create(client, world, b"data", role=role, tablet=tablet_id)
    assert response.status_code == status, response.text


def test_others_cannot_touch_an_upload(client, world):
    upload_id = create(client, world, b"q" * 10).json()["id"]
    assert put(client, world, upload_id, 0, b"q" * 10, role="staff_other").status_code == 404
    assert put(client, world, upload_id, 0, b"q" * 10, role="reader").status_code == 404
    assert complete(client, world, upload_id, sha(b"q" * 10), role="anonymous").status_code == 401
    assert put(client, world, upload_id, 0, b"q" * 10, role="admin").status_code == 200
    missing = "00000000-0000-4000-8000-000000000000"
    assert put(client, world, missing, 0, b"q").status_code == 404


def test_a_broken_connection_keeps_what_arrived(client, world, app):
    """The client vanishes after 10 of 40 bytes: those 10 are on disk and recorded."""
    import asyncio

    upload_id = create(client, world, b"b" * 40).json()["id"]
    messages = [
        {"type": "http.request", "body": b"a" * 10, "more_body": True},
        {"type": "http.disconnect"},
    ]

    async def receive():
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    async def send(_message):
        pass

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "PUT",
        "scheme": "http",
        "path": f"{API}/uploads/{upload_id}/chunks",
        "raw_path": f"{API}/uploads/{upload_id}/chunks".encode(),
        "query_string": b"offset=20",
        "root_path": "",
        "headers": [
            (b"host", b"testserver"),
            (b"authorization", world.headers("staff_own")["Authorization"].encode()),
            (b"content-type", b"application/octet-stream"),
            (b"content-length", b"20"),
        ],
        "server": ("testserver", 80),
        "client": ("127.0.0.1", 5000),
    }
    asyncio.run(app(scope, receive, send))
    state = client.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own")).json()
    assert state["ranges"] == [[20, 30]]
    part = app.state.settings.data_dir / "uploads" / f"{upload_id}.part"
    assert part.read_bytes()[20:30] == b"a" * 10


def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_full_disk_at_creation_is_507_and_keeps_nothing(client, world, app, monkeypatch):
    monkeypatch.setattr(uploads_mod.os, "open", _no_space)
    response = create(client, world, b"x" * 1000)
    assert response.status_code == 507
    assert response.json() == {"detail": "storage is full: nothing was stored", "where": "storage"}
    monkeypatch.undo()
    assert list((app.state.settings.data_dir / "uploads").iterdir()) == []
    with world.session() as session:
        assert session.scalars(select(Upload)).all() == []


def test_full_disk_during_a_chunk_is_507_and_records_nothing(client, world, monkeypatch):
    upload_id = create(client, world, b"x" * 100).json()["id"]
    monkeypatch.setattr(api_uploads_mod.os, "pwrite", _no_space)
    response = put(client, world, upload_id, 0, b"y" * 100)
    assert response.status_code == 507
    monkeypatch.undo()
    state = client.get(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own")).json()
    assert state["ranges"] == [] and state["state"] == "open"


def test_full_storage_at_completion_keeps_the_upload_open(
    client, world, dispatcher, app, tmp_path, monkeypatch
):
    data = bundle_bytes(tmp_path)
    upload_id = create(client, world, data).json()["id"]
    put(client, world, upload_id, 0, data)
    store = LocalStorage(app.state.settings.resolved_storage_dir)
    app.state.storage = store
    monkeypatch.setattr(storage_mod.os, "fsync", _no_space)
    response = complete(client, world, upload_id, sha(data))
    assert response.status_code == 507 and response.json()["where"] == "storage"
    monkeypatch.undo()
    assert store.list() == [] and dispatcher.sent == []
    scans = client.get(f"{API}/tablets/{world.private_a}/scans", headers=world.headers("admin"))
    assert scans.json() == []
    # Space freed: completing again works, from the bytes already received.
    assert complete(client, world, upload_id, sha(data)).status_code == 201


def test_expire_stale_uploads(client, world, app):
    from datetime import UTC, datetime, timedelta

    from backend.uploads import expire_uploads

    uploads_dir = app.state.settings.data_dir / "uploads"
    old_id = create(client, world, b"o" * 10).json()["id"]
    fresh_id = create(client, world, b"f" * 10).json()["id"]
    orphan = uploads_dir / "00000000-0000-4000-8000-000000000001.part"
    orphan.write_bytes(b"left by a crash")
    os.utime(orphan, (0, 0))
    with world.session() as session:
        session.get(Upload, old_id).updated_at = datetime.now(UTC) - timedelta(days=8)
    with world.session() as session:
        with pytest.raises(ValueError, match="older_than"):
            expire_uploads(session, uploads_dir=uploads_dir, older_than=timedelta(0))
        assert expire_uploads(session, uploads_dir=uploads_dir, older_than=timedelta(days=7)) == 1
    headers = world.headers("staff_own")
    assert client.get(f"{API}/uploads/{old_id}", headers=headers).status_code == 404
    assert client.get(f"{API}/uploads/{fresh_id}", headers=headers).status_code == 200
    assert sorted(p.name for p in uploads_dir.iterdir()) == [f"{fresh_id}.part"]


def test_bundles_go_to_s3_when_configured(client, world, dispatcher, app, tmp_path):
    from moto.server import ThreadedMotoServer

    from backend.storage import S3Storage

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        store = S3Storage(
            bucket="bundles-test",
            endpoint_url=f"http://{host}:{port}",
            access_key_id="testing",
            secret_access_key="testing",
        )
        store.ensure_bucket()
        app.state.storage = store
        data = bundle_bytes(tmp_path, scan_id="rig-s3")
        _, response = upload_all(client, world, data, chunk=2000)
        assert response.status_code == 201
        (key,) = store.list("scans/")
        assert store.read_bytes(key) == data and store.stat(key).etag == sha(data)
    finally:
        server.stop()
