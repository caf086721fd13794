"""The job state machine (backend.jobs) as the worker uses it, and the jobs API."""

from __future__ import annotations

import json
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from backend import jobs
from backend.jobs import JobStateError, RecordingDispatcher
from backend.storage import LocalStorage, StorageError
from backend.tables import Job, JobState, Model, Scan, Tablet

API = "/api/v1"


@pytest.fixture
def db_url(sqlite_url) -> str:
    return sqlite_url


@pytest.fixture
def store(app) -> LocalStorage:
    store = LocalStorage(app.state.settings.resolved_storage_dir)
    app.state.storage = store
    return store


def new_job(world, *, tablet_id: int, face: str = "obverse", uid: str | None = None) -> int:
    with world.session() as session:
        scan = Scan(
            tablet_id=tablet_id,
            face=face,
            scan_uid=uid,
            bundle_key=f"scans/{tablet_id}/x/bundle.zip",
            bundle_sha256="0" * 64,
            size_bytes=1,
            manifest={},
        )
        session.add(scan)
        session.flush()
        return jobs.create(session, scan=scan).id


def model_dir(tmp_path: Path, *, name: str = "model") -> Path:
    out = tmp_path / name
    (out / "quality").mkdir(parents=True)
    (out / "model.glb").write_bytes(b"glTF" + bytes(60))
    (out / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")
    (out / "thumbnail.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(20))
    (out / "report.json").write_text(json.dumps({"pixel_size_um": 50, "timings_s": {"a": 1}}))
    (out / "quality" / "residual.npy").write_bytes(b"\x93NUMPY")
    return out


def test_happy_path_stores_the_model_in_one_go(world, store, tmp_path):
    job_id = new_job(world, tablet_id=world.private_a)
    with world.session() as session:
        job = jobs.mark_running(session, job_id=job_id)
        assert job.state == JobState.running and job.attempts == 1
        jobs.report_progress(
            session, job_id=job_id, stage="photometric", fraction=0.4, timings_s={"load": 1.5}
        )
        jobs.report_progress(session, job_id=job_id, stage="mesh", fraction=0.9, timings_s={"x": 2})
        model = jobs.mark_succeeded(
            session, job_id=job_id, model_dir=model_dir(tmp_path), storage=store
        )
    with world.session() as session:
        job = session.get(Job, job_id)
        assert job.state == JobState.succeeded and job.progress == 1.0
        assert job.timings == {"load": 1.5, "x": 2.0} and job.model_id == model.id
        model = session.get(Model, model.id)
        assert model.version == 1 and model.report["pixel_size_um"] == 50
        assert set(model.assets) == {
            "model.glb",
            "mesh.ply",
            "thumbnail.png",
            "report.json",
            "quality/residual.npy",
        }
        assert session.get(Tablet, world.private_a).has_3d
        prefix = model.storage_prefix
    assert store.read_bytes(f"{prefix}/model.glb") == b"glTF" + bytes(60)
    # Delivered twice (acks_late): the same model, nothing stored again.
    with world.session() as session:
        again = jobs.mark_succeeded(
            session, job_id=job_id, model_dir=model_dir(tmp_path, name="m2"), storage=store
        )
        assert again.id == model.id
    assert len(store.list("models/")) == 5


def test_a_rescan_adds_a_version_and_never_overwrites(world, store, tmp_path):
    first_dir = model_dir(tmp_path, name="one")
    second_dir = model_dir(tmp_path, name="two")
    (second_dir / "model.glb").write_bytes(b"glTF second")
    versions = []
    for directory, face in [(first_dir, "obverse"), (second_dir, "obverse"), (first_dir, "top")]:
        job_id = new_job(world, tablet_id=world.public_a, face=face)
        with world.session() as session:
            jobs.mark_running(session, job_id=job_id)
            model = jobs.mark_succeeded(session, job_id=job_id, model_dir=directory, storage=store)
            versions.append((model.version, model.storage_prefix))
    assert [v for v, _ in versions] == [1, 2, 1]
    assert len({p for _, p in versions}) == 3
    assert [p.split("/")[2:4][0] for _, p in versions] == ["obverse", "obverse", "top"]
    assert [p.split("/")[3].split("-")[0] for _, p in versions] == ["v1", "v2", "v1"]
    assert store.read_bytes(f"{versions[0][1]}/model.glb") == b"glTF" + bytes(60)
    assert store.read_bytes(f"{versions[1][1]}/model.glb") == b"glTF second"


def test_failed_commit_removes_the_stored_files(world, store, tmp_path, monkeypatch):
    job_id = new_job(world, tablet_id=world.private_a)
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
    with world.session() as session:

        def broken_commit():
            raise RuntimeError("database went away")

        monkeypatch.setattr(session, "commit", broken_commit)
        with pytest.raises(RuntimeError):
            jobs.mark_succeeded(
                session, job_id=job_id, model_dir=model_dir(tmp_path), storage=store
            )
        monkeypatch.undo()
    assert store.list("models/") == []
    with world.session() as session:
        assert session.get(Job, job_id).state == JobState.running
        assert session.scalars(select(Model)).all() == []


def test_storage_failure_leaves_the_job_running(world, store, tmp_path, monkeypatch):
    job_id = new_job(world, tablet_id=world.private_a)
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)

    def full(*args, **kwargs):
        raise StorageError("storage is full: nothing was stored", status_code=507)

    monkeypatch.setattr(store, "put_file", full)
    with world.session() as session, pytest.raises(StorageError):
        jobs.mark_succeeded(session, job_id=job_id, model_dir=model_dir(tmp_path), storage=store)
    with world.session() as session:
        assert session.get(Job, job_id).state == JobState.running


def test_illegal_transitions(world, store, tmp_path):
    job_id = new_job(world, tablet_id=world.private_a)
    with world.session() as session:
        with pytest.raises(JobStateError, match="queued"):
            jobs.report_progress(session, job_id=job_id, stage="x", fraction=0.1)
        with pytest.raises(JobStateError):
            jobs.retry(session, job_id=job_id)
        with pytest.raises(JobStateError):
            jobs.mark_succeeded(
                session, job_id=job_id, model_dir=model_dir(tmp_path), storage=store
            )
        jobs.mark_running(session, job_id=job_id)
        for bad in (-0.1, 1.5, float("nan")):
            with pytest.raises(ValueError, match="fraction"):
                jobs.report_progress(session, job_id=job_id, stage="x", fraction=bad)
        with pytest.raises(ValueError, match="timings_s"):
            jobs.report_progress(
                session, job_id=job_id, stage="x", fraction=0.5, timings_s={"a": -1}
            )
        with pytest.raises(ValueError, match="model.glb"):
            jobs.mark_succeeded(session, job_id=job_id, model_dir=tmp_path, storage=store)
        job = jobs.mark_failed(session, job_id=job_id, error="integration diverged")
        assert job.state == JobState.failed and job.finished_at is not None
        with pytest.raises(JobStateError):
            jobs.mark_running(session, job_id=job_id)
        with pytest.raises(JobStateError):
            jobs.mark_failed(session, job_id=job_id, error="again")
        with pytest.raises(LookupError, match="job_id"):
            jobs.mark_running(session, job_id=987654)


def test_retry_through_the_api(client, world, app):
    app.state.dispatcher = RecordingDispatcher()
    job_id = new_job(world, tablet_id=world.private_a)
    url = f"{API}/jobs/{job_id}"
    staff = world.headers("staff_own")
    assert client.post(f"{url}/retry", headers=staff).status_code == 409  # queued
    with world.session() as session:
        jobs.mark_running(session, job_id=job_id)
        jobs.report_progress(session, job_id=job_id, stage="fringe", fraction=0.5)
        jobs.mark_failed(session, job_id=job_id, error="fringe unwrapping failed at period 3")
    body = client.get(url, headers=staff).json()
    assert body["state"] == "failed" and body["error"].startswith("fringe unwrapping")
    assert body["stage"] == "fringe" and body["attempts"] == 1
    assert client.post(f"{url}/retry", headers=world.headers("reader")).status_code == 404
    assert client.post(f"{url}/retry", headers=world.headers("staff_other")).status_code == 404
    assert client.post(f"{url}/retry").status_code == 404  # private: not revealed
    retried = client.post(f"{url}/retry", headers=staff)
    assert retried.status_code == 200
    assert retried.json()["state"] == "queued" and retried.json()["error"] is None
    assert app.state.dispatcher.sent == [
        (jobs.RECONSTRUCT_TASK, [job_id], f"job-{job_id}-attempt-2")
    ]


def test_public_job_staff_of_others_get_403_on_retry(client, world, app):
    app.state.dispatcher = RecordingDispatcher()
    job_id = new_job(world, tablet_id=world.public_a)
    with world.session() as session:
        jobs.mark_failed(session, job_id=job_id, error="no frames")
    assert client.get(f"{API}/jobs/{job_id}").status_code == 200  # public tablet: readable
    assert client.post(f"{API}/jobs/{job_id}/retry").status_code == 401
    response = client.post(f"{API}/jobs/{job_id}/retry", headers=world.headers("staff_other"))
    assert response.status_code == 403
    assert (
        client.post(f"{API}/jobs/{job_id}/retry", headers=world.headers("admin")).status_code == 200
    )


def test_a_dead_broker_leaves_the_retried_job_queued_awaiting_dispatch(client, world, app):
    class DeadBroker:
        def send_task(self, name, *, args, task_id):
            raise ConnectionRefusedError("redis down")

    app.state.dispatcher = DeadBroker()
    job_id = new_job(world, tablet_id=world.private_a)
    with world.session() as session:
        jobs.mark_failed(session, job_id=job_id, error="first try failed")
    response = client.post(f"{API}/jobs/{job_id}/retry", headers=world.headers("admin"))
    assert response.status_code == 200
    body = response.json()
    assert body["state"] == "queued" and body["error"] is None
    assert body["awaiting_dispatch"] and body["stage"] == jobs.AWAITING_DISPATCH
    assert body["enqueued_at"] is None
    # The broker is back: the sweeper's dispatcher loop sends it once its backoff passed.
    from backend.dispatch import dispatch_due

    sent = RecordingDispatcher()
    with world.session() as session:
        later = jobs.now_utc() + timedelta(seconds=2)
        assert dispatch_due(session, sent, backoff_max_s=60, now=later) == [job_id]
    assert sent.sent == [(jobs.RECONSTRUCT_TASK, [job_id], f"job-{job_id}-attempt-1")]
    body = client.get(f"{API}/jobs/{job_id}", headers=world.headers("admin")).json()
    assert body["state"] == "queued" and not body["awaiting_dispatch"]
    assert body["enqueued_at"] is not None and body["stage"] is None


def test_celery_dispatcher_sends_by_name_to_the_queue(monkeypatch):
    sent = {}

    class FakeCelery:
        def __init__(self, main, broker):
            sent["broker"] = broker

        def send_task(self, name, **kwargs):
            sent["name"], sent["kwargs"] = name, kwargs

    import celery

    monkeypatch.setattr(celery, "Celery", FakeCelery)
    dispatcher = jobs.CeleryDispatcher(broker_url="redis://127.0.0.1:1/0", queue="reconstruct")
    dispatcher.send_task(jobs.RECONSTRUCT_TASK, args=[5], task_id="job-5-attempt-1")
    assert sent["broker"] == "redis://127.0.0.1:1/0"
    assert sent["name"] == "worker.tasks.reconstruct_scan"
    assert sent["kwargs"]["args"] == [5] and sent["kwargs"]["queue"] == "reconstruct"


@pytest.mark.redis
def test_celery_dispatcher_publishes_to_a_real_redis(tmp_path):
    import json
    import socket
    import subprocess
    import time

    import redis

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = subprocess.Popen(
        [
            "redis-server",
            "--port",
            str(port),
            "--save",
            "",
            "--appendonly",
            "no",
            "--dir",
            tmp_path,
        ],
        stdout=subprocess.DEVNULL,
    )
    try:
        client = redis.Redis(port=port)
        for _ in range(100):
            try:
                client.ping()
                break
            except redis.ConnectionError:
                time.sleep(0.05)
        dispatcher = jobs.CeleryDispatcher(
            broker_url=f"redis://127.0.0.1:{port}/0", queue="reconstruct"
        )
        dispatcher.send_task(jobs.RECONSTRUCT_TASK, args=[42], task_id="job-42-attempt-1")
        (message,) = client.lrange("reconstruct", 0, -1)
        headers = json.loads(message)["headers"]
        assert headers["task"] == "worker.tasks.reconstruct_scan"
        assert headers["id"] == "job-42-attempt-1" and headers["argsrepr"] == "[42]"
        client.close()
    finally:
        server.terminate()
        server.wait(timeout=10)
