"""Upload limits on both databases: nothing reserved up front, the per-institution quota
(checked at creation and as bytes arrive), the free-disk margin, expiry giving bytes back,
and a reused ``scan.id`` (409 naming the scan, bytes kept)."""

from __future__ import annotations

import asyncio
import os
import random
import threading
from datetime import UTC, datetime, timedelta

import pytest
import test_uploads as helpers  # the bundle helpers (tests/backend is on pythonpath)

from backend import uploads as uploads_mod
from backend.api import uploads as api_uploads_mod
from backend.jobs import RecordingDispatcher
from backend.tables import Scan, Upload

API = "/api/v1"


def limit(app, **values) -> None:
    """Replace upload settings of the running app (routes read app.state.settings)."""
    app.state.settings = app.state.settings.model_copy(update=values)


def stored_scan(world, tablet_id: int, size_bytes: int) -> int:
    scan_id = world.new_scan(tablet_id)
    with world.session() as session:
        session.get(Scan, scan_id).size_bytes = size_bytes
    return scan_id


def usage(world, institution_id: int) -> int:
    with world.session() as session:
        return uploads_mod.institution_usage_bytes(session, institution_id=institution_id)


def state(client, world, upload_id, role="staff_own"):
    return client.get(f"{API}/uploads/{upload_id}", headers=world.headers(role))


def test_declared_size_reserves_no_disk(client, world, app):
    limit(app, upload_min_free_bytes=0)
    declared = 19 * 1024**3
    response = client.post(
        f"{API}/uploads",
        json={"tablet_id": world.private_a, "filename": "big.zip", "size_bytes": declared},
        headers=world.headers("staff_own"),
    )
    assert response.status_code == 201, response.text
    upload_id = response.json()["id"]
    part = app.state.settings.data_dir / "uploads" / f"{upload_id}.part"
    assert part.stat().st_size == 0 and part.stat().st_blocks == 0
    assert helpers.put(client, world, upload_id, 1024**3, b"t" * 4096).status_code == 200
    # Sparse: a chunk at 1 GiB allocates its own blocks, not the gap before it.
    assert part.stat().st_blocks * 512 < 1024**2
    assert usage(world, world.institution_a) == 4096


def test_quota_counts_scans_and_open_uploads_at_creation(client, world, app):
    limit(app, upload_quota_bytes=1000)
    stored_scan(world, world.private_a, 600)
    refused = helpers.create(client, world, b"x" * 401)
    assert refused.status_code == 413
    body = refused.json()
    assert body["where"] == "size_bytes"
    assert "'Museum A'" in body["detail"] and "600 of 1000 bytes used" in body["detail"]
    assert helpers.create(client, world, b"x" * 400).status_code == 201
    # Another institution has its own quota.
    other = helpers.create(client, world, b"x" * 900, role="staff_other", tablet=world.private_b)
    assert other.status_code == 201
    # Over the per-upload maximum is refused before the quota is even asked.
    limit(app, upload_max_bytes=100)
    assert helpers.create(client, world, b"x" * 101).json()["where"] == "size_bytes"


def test_quota_is_checked_again_as_chunks_arrive(client, world, app):
    limit(app, upload_quota_bytes=1000)
    first = helpers.create(client, world, b"a" * 800).json()["id"]
    second = helpers.create(client, world, b"b" * 800).json()["id"]  # declared: not counted
    assert helpers.put(client, world, first, 0, b"a" * 800).status_code == 200
    assert usage(world, world.institution_a) == 800

    refused = helpers.put(client, world, second, 0, b"b" * 300)
    assert refused.status_code == 413 and refused.json()["where"] == "offset"
    assert "800 of 1000 bytes used" in refused.json()["detail"]
    assert state(client, world, second).json()["ranges"] == []

    assert helpers.put(client, world, second, 0, b"b" * 200).status_code == 200
    # Bytes received before count once: sending them again adds nothing.
    assert helpers.put(client, world, first, 0, b"a" * 800).status_code == 200
    assert helpers.put(client, world, second, 100, b"b" * 100).status_code == 200
    assert helpers.put(client, world, second, 200, b"b").status_code == 413
    assert usage(world, world.institution_a) == 1000


def test_a_body_without_length_is_cut_off_at_the_quota(client, world, app, monkeypatch):
    """No Content-Length to check up front: the bytes that fit are kept, then 413."""
    monkeypatch.setattr(api_uploads_mod, "WRITE_BUFFER_BYTES", 100)
    limit(app, upload_quota_bytes=1000)
    upload_id = helpers.create(client, world, b"c" * 900).json()["id"]
    stored_scan(world, world.private_a, 470)  # stored after creation: 530 bytes left

    # Raw ASGI: 18 pieces of 50 bytes and no Content-Length (TestClient would send one).
    messages = [{"type": "http.request", "body": b"c" * 50, "more_body": True}] * 18
    messages.append({"type": "http.request", "body": b"", "more_body": False})
    sent = []

    async def receive():
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    async def send(message):
        sent.append(message)

    path = f"{API}/uploads/{upload_id}/chunks"
    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "PUT",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"offset=0",
        "root_path": "",
        "headers": [
            (b"host", b"testserver"),
            (b"authorization", world.headers("staff_own")["Authorization"].encode()),
            (b"content-type", b"application/octet-stream"),
            (b"transfer-encoding", b"chunked"),
        ],
        "server": ("testserver", 80),
        "client": ("127.0.0.1", 5000),
    }
    asyncio.run(app(scope, receive, send))
    status = next(m["status"] for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    assert status == 413, body
    assert b"470 of 1000 bytes used" in body
    # Every byte that fits is kept, to the byte (not to the 100-byte write buffer).
    assert state(client, world, upload_id).json()["ranges"] == [[0, 530]]
    part = app.state.settings.data_dir / "uploads" / f"{upload_id}.part"
    assert part.read_bytes() == b"c" * 530


def test_free_disk_margin(client, world, app):
    limit(app, upload_min_free_bytes=1 << 62)
    response = helpers.create(client, world, b"d" * 10)
    assert response.status_code == 507 and response.json()["where"] == "storage"
    assert "nearly full" in response.json()["detail"]
    limit(app, upload_min_free_bytes=0)
    upload_id = helpers.create(client, world, b"d" * 10).json()["id"]
    limit(app, upload_min_free_bytes=1 << 62)
    response = helpers.put(client, world, upload_id, 0, b"d" * 10)
    assert response.status_code == 507 and "nearly full" in response.json()["detail"]
    assert state(client, world, upload_id).json()["ranges"] == []
    limit(app, upload_min_free_bytes=0)
    assert helpers.put(client, world, upload_id, 0, b"d" * 10).status_code == 200


def test_expiry_gives_the_bytes_back_and_is_idempotent(client, world, app):
    limit(app, upload_quota_bytes=1000)
    uploads_dir = app.state.settings.data_dir / "uploads"
    stale = helpers.create(client, world, b"e" * 800).json()["id"]
    assert helpers.put(client, world, stale, 0, b"e" * 800).status_code == 200
    fresh = helpers.create(client, world, b"f" * 100).json()["id"]
    assert helpers.create(client, world, b"g" * 300).status_code == 413
    week = timedelta(days=7)
    with world.session() as session:
        session.get(Upload, stale).updated_at = datetime.now(UTC) - timedelta(days=8)
    with world.session() as session:
        loaded = session.get(Upload, stale)  # a session that holds the row it deletes
        assert loaded is not None
        assert uploads_mod.expire_uploads(session, uploads_dir=uploads_dir, older_than=week) == 1
    with world.session() as session:
        assert uploads_mod.expire_uploads(session, uploads_dir=uploads_dir, older_than=week) == 0
    assert state(client, world, stale).status_code == 404
    assert state(client, world, fresh).status_code == 200
    assert sorted(p.name for p in uploads_dir.iterdir()) == [f"{fresh}.part"]
    assert usage(world, world.institution_a) == 0
    assert helpers.create(client, world, b"g" * 300).status_code == 201


def test_expiry_leaves_young_orphans_and_foreign_files(client, world, app):
    uploads_dir = app.state.settings.data_dir / "uploads"
    uploads_dir.mkdir(parents=True, exist_ok=True)
    young = uploads_dir / "00000000-0000-4000-8000-000000000002.part"
    old = uploads_dir / "00000000-0000-4000-8000-000000000003.part"
    foreign = uploads_dir / "notes.part"
    for path in (young, old, foreign):
        path.write_bytes(b"x")
    os.utime(old, (0, 0))
    os.utime(foreign, (0, 0))
    with world.session() as session:
        uploads_mod.expire_uploads(session, uploads_dir=uploads_dir, older_than=timedelta(days=1))
    assert sorted(p.name for p in uploads_dir.iterdir()) == sorted([young.name, foreign.name])


@pytest.fixture
def dispatcher(app) -> RecordingDispatcher:
    app.state.dispatcher = RecordingDispatcher()
    return app.state.dispatcher


def test_reused_scan_id_with_other_content_is_409_and_keeps_the_bytes(
    client, world, app, dispatcher, tmp_path
):
    original = helpers.bundle_bytes(tmp_path, scan_id="rig-reused", face="obverse")
    _, first = helpers.upload_all(client, world, original)
    assert first.status_code == 201
    scan_id = first.json()["scan"]["id"]

    other = helpers.bundle_bytes(tmp_path, scan_id="rig-reused", face="reverse")
    upload_id, response = helpers.upload_all(client, world, other)
    assert response.status_code == 409
    body = response.json()
    assert body["where"] == "manifest.scan.id"
    assert f"scan {scan_id} ({API}/scans/{scan_id})" in body["detail"]
    assert "other content" in body["detail"] and upload_id in body["detail"]
    # Nothing silently lost: the upload is open with every byte, asking again is the same.
    kept = state(client, world, upload_id).json()
    assert kept["state"] == "open" and kept["received_bytes"] == len(other)
    part = app.state.settings.data_dir / "uploads" / f"{upload_id}.part"
    assert part.read_bytes() == other
    again = helpers.complete(client, world, upload_id, helpers.sha(other))
    assert again.status_code == 409 and again.json()["detail"] == body["detail"]
    assert len(dispatcher.sent) == 1
    named = client.get(f"{API}/scans/{scan_id}", headers=world.headers("staff_own"))
    assert named.status_code == 200 and named.json()["scan_uid"] == "rig-reused"
    listed = client.get(f"{API}/tablets/{world.private_a}/scans", headers=world.headers("admin"))
    assert [s["id"] for s in listed.json()] == [scan_id]
    # The client decides: discard.
    discard = client.delete(f"{API}/uploads/{upload_id}", headers=world.headers("staff_own"))
    assert discard.status_code == 204 and not part.exists()

    # The same content again stays idempotent.
    _, same = helpers.upload_all(client, world, original)
    assert same.status_code == 200 and same.json()["scan"]["id"] == scan_id


def test_reused_scan_id_on_another_tablet_names_the_scan(client, world, dispatcher, tmp_path):
    data = helpers.bundle_bytes(tmp_path, scan_id="rig-moved")
    scan_id = helpers.upload_all(client, world, data)[1].json()["scan"]["id"]
    upload_id, response = helpers.upload_all(client, world, data, tablet=world.public_a)
    assert response.status_code == 409
    assert f"{API}/scans/{scan_id}" in response.json()["detail"]
    assert f"another tablet ({world.private_a})" in response.json()["detail"]
    assert state(client, world, upload_id).json()["state"] == "open"


def test_reused_scan_id_of_a_hidden_scan_reveals_nothing(client, world, dispatcher, tmp_path):
    data = helpers.bundle_bytes(tmp_path, scan_id="rig-hidden")
    scan_id = helpers.upload_all(client, world, data)[1].json()["scan"]["id"]
    response = client.post(
        f"{API}/uploads",
        json={"tablet_id": world.private_b, "filename": "b.zip", "size_bytes": len(data)},
        headers=world.headers("staff_other"),
    )
    upload_id = response.json()["id"]
    assert helpers.put(client, world, upload_id, 0, data, role="staff_other").status_code == 200
    response = helpers.complete(client, world, upload_id, helpers.sha(data), role="staff_other")
    assert response.status_code == 409 and response.json()["where"] == "manifest.scan.id"
    detail = response.json()["detail"]
    assert "/scans/" not in detail and f"scan {scan_id}" not in detail
    assert str(world.private_a) not in detail.replace(upload_id, "")


def test_new_bytes_matches_counting_byte_by_byte():
    rng = random.Random(16)
    for _ in range(300):
        ranges: list[list[int]] = []
        for _ in range(rng.randrange(5)):
            lo = rng.randrange(100)
            ranges = uploads_mod.merge_range(ranges, lo, lo + rng.randrange(20))
        start = rng.randrange(110)
        end = start + rng.randrange(30)
        covered = {i for lo, hi in ranges for i in range(lo, hi)}
        expected = sum(1 for i in range(start, end) if i not in covered)
        assert uploads_mod.new_bytes(ranges, start, end) == expected
    with pytest.raises(ValueError, match="start <= end"):
        uploads_mod.new_bytes([], 5, 4)


def test_fitting_prefix_counts_only_new_bytes():
    budget = uploads_mod.Budget(institution="institution 'M'", used_bytes=90, quota_bytes=100)
    # [0, 5) was received before: 10 new bytes fit after it, so 15 of the 20 bytes.
    assert budget.fitting_prefix([[0, 5]], 0, 0, 20) == 15
    assert budget.fitting_prefix([], 0, 4, 20) == 6  # 4 new bytes written already
    assert uploads_mod.Budget(None, 0, None).fitting_prefix([], 0, 0, 7) == 7


def test_two_sweeps_at_once_delete_each_upload_once(client, world, app, db_url):
    """PostgreSQL: the second sweep waits on the first's row lock, then deletes nothing.

    (SQLite serialises writers: there the later sweep fails with "database is locked" and
    deletes nothing either; it simply runs again next time.)
    """
    if not db_url.startswith("postgresql"):
        pytest.skip("row locks between two sweeps: PostgreSQL only")
    uploads_dir = app.state.settings.data_dir / "uploads"
    stale = helpers.create(client, world, b"s" * 10).json()["id"]
    with world.session() as session:
        session.get(Upload, stale).updated_at = datetime.now(UTC) - timedelta(days=8)
    factory, week, counts = app.state.sessionmaker, timedelta(days=7), {}

    def sweep(name):
        with factory() as session:
            counts[name] = uploads_mod.expire_uploads(
                session, uploads_dir=uploads_dir, older_than=week
            )
            session.commit()

    first = factory()
    counts["first"] = uploads_mod.expire_uploads(first, uploads_dir=uploads_dir, older_than=week)
    second = threading.Thread(target=sweep, args=("second",))
    second.start()
    second.join(timeout=0.5)
    assert second.is_alive()  # waiting for the first sweep's lock
    first.commit()
    first.close()
    second.join(timeout=30)
    assert counts == {"first": 1, "second": 0}
    assert not (uploads_dir / f"{stale}.part").exists()
