"""The upload path on both databases (SQLite and PostgreSQL): protocol and concurrent chunks."""

from __future__ import annotations

import hashlib
import threading

import pytest
import test_uploads as helpers  # the bundle helpers (tests/backend is on pythonpath)

from backend.jobs import RecordingDispatcher
from backend.tables import Upload
from backend.uploads import record_range

API = "/api/v1"


def test_protocol_on_each_database(client, world, app, tmp_path):
    app.state.dispatcher = RecordingDispatcher()
    data = helpers.bundle_bytes(tmp_path, scan_id="rig-db")
    upload_id = helpers.create(client, world, data).json()["id"]
    half = len(data) // 2
    assert helpers.put(client, world, upload_id, half, data[half:]).status_code == 200
    assert helpers.put(client, world, upload_id, 0, data[:half]).status_code == 200
    response = helpers.complete(client, world, upload_id, hashlib.sha256(data).hexdigest())
    assert response.status_code == 201, response.text
    again = helpers.upload_all(client, world, data)[1]
    assert again.status_code == 200
    assert again.json()["scan"]["id"] == response.json()["scan"]["id"]


def test_concurrent_chunks_lose_no_range(client, world, app):
    """Eight threads record disjoint ranges of one upload at once: all must be kept.

    Each thread's read-modify-write of ``uploads.ranges`` races the others; without the
    optimistic lock (``uploads.revision``) some ranges would be overwritten.
    """
    n, chunk = 8, 100
    upload_id = helpers.create(client, world, b"x" * (n * chunk)).json()["id"]
    factory = app.state.sessionmaker
    barrier = threading.Barrier(n)
    errors = []

    def record(i: int) -> None:
        try:
            barrier.wait()
            record_range(factory, upload_id=upload_id, start=i * chunk, end=(i + 1) * chunk)
        except Exception as exc:  # collected and reported below
            errors.append(exc)

    threads = [threading.Thread(target=record, args=(i,)) for i in (0, 2, 4, 6, 1, 3, 5, 7)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    with factory() as session:
        assert session.get(Upload, upload_id).ranges == [[0, n * chunk]]


@pytest.mark.parametrize("role", ["staff_own", "admin"])
def test_upload_state_visible_to_editors(client, world, role):
    upload_id = helpers.create(client, world, b"abc").json()["id"]
    response = client.get(f"{API}/uploads/{upload_id}", headers=world.headers(role))
    assert response.status_code == 200
    assert response.json()["missing"] == [[0, 3]]


@pytest.mark.parametrize("scan_uid", [None, "rig-race"])
def test_two_completions_of_one_upload_make_one_scan(client, world, app, tmp_path, scan_uid):
    """A client that times out and asks again while the first completion still runs."""
    from sqlalchemy import select

    from backend.storage import LocalStorage
    from backend.tables import Scan, User
    from backend.uploads import complete_upload

    data = helpers.bundle_bytes(tmp_path, scan_id=scan_uid)
    upload_id = helpers.create(client, world, data).json()["id"]
    helpers.put(client, world, upload_id, 0, data)
    store = LocalStorage(app.state.settings.resolved_storage_dir)
    factory = app.state.sessionmaker
    barrier = threading.Barrier(2)
    results, errors = [], []

    def finish() -> None:
        with factory() as session:
            upload = session.get(Upload, upload_id)
            user = session.get(User, world.users["staff_own"])
            barrier.wait()
            try:
                done = complete_upload(
                    session,
                    upload=upload,
                    sha256=hashlib.sha256(data).hexdigest(),
                    uploads_dir=app.state.settings.data_dir / "uploads",
                    storage=store,
                    user=user,
                    api_prefix=app.state.settings.api_prefix,
                )
                results.append((done.scan.id, done.job.id, done.created))
            except Exception as exc:  # reported below
                errors.append(exc)

    threads = [threading.Thread(target=finish) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert len({(scan, job) for scan, job, _ in results}) == 1
    assert sorted(created for *_, created in results) == [False, True]
    with factory() as session:
        (scan,) = session.scalars(select(Scan)).all()
        assert store.list("scans/") == [scan.bundle_key]
        assert store.read_bytes(scan.bundle_key) == data
