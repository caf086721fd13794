"""The upload path on both databases (SQLite and PostgreSQL): protocol and concurrent chunks."""

from __future__ import annotations

import hashlib
import importlib.util
import threading
from pathlib import Path

import pytest

from backend.jobs import RecordingDispatcher
from backend.tables import Upload
from backend.uploads import record_range

API = "/api/v1"


def _load_helpers():
    # The bundle helpers live in test_uploads.py; load that module by path (importlib mode).
    spec = importlib.util.spec_from_file_location(
        "upload_helpers", Path(__file__).with_name("test_uploads.py")
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


helpers = _load_helpers()


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
