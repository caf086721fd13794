"""worker.tasks in-process (the system tests run real workers): a reconstruction job stores one
model with its derived assets, timings and progress; redelivery does no work twice; a job
running elsewhere is left alone; transient errors are the named ones."""

from __future__ import annotations

import hashlib
import shutil
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import pytest
from sqlalchemy import func, select
from sqlalchemy.exc import OperationalError

from backend import jobs
from backend.db import migrate
from backend.settings import Settings
from backend.storage import ObjectNotFound, StorageError, storage_from_settings
from backend.tables import Job, JobKind, JobState, Model, Scan, Tablet
from worker import celery_app as capp
from worker import tasks


@pytest.fixture
def env(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", _env_file=None, job_stale_after_s=30)
    migrate(settings.resolved_database_url)
    previous = capp.settings
    capp.configure(settings)
    yield settings
    capp.configure(previous)


@pytest.fixture(scope="module")
def bundle_zip(tmp_path_factory):
    from worker.simulate import simulate_scan

    out = tmp_path_factory.mktemp("bundle")
    result = simulate_scan(out / "sim", seed=5, face="obverse", preset="quick", size=(64, 80))
    return shutil.make_archive(str(out / "bundle"), "zip", result.bundles["obverse"])


def _scan_job(settings, bundle_zip=None) -> int:
    storage = storage_from_settings(settings)
    key = "scans/1/test/bundle.zip"
    data = Path(bundle_zip).read_bytes() if bundle_zip else b"not a bundle"
    storage.put_bytes(key, data)
    with capp.session_factory()() as session:
        tablet = Tablet(designation="t")
        session.add(tablet)
        session.flush()
        scan = Scan(
            tablet_id=tablet.id,
            face="obverse",
            bundle_key=key,
            bundle_sha256=hashlib.sha256(data).hexdigest(),
            size_bytes=len(data),
        )
        session.add(scan)
        session.flush()
        job = jobs.create(session, scan=scan)
        session.commit()
        return job.id


def _row(job_id: int) -> Job:
    with capp.session_factory()() as session:
        return session.get(Job, job_id)


def test_reconstruction_job_stores_one_model_with_assets_and_redelivery_is_a_no_op(env, bundle_zip):
    job_id = _scan_job(env, bundle_zip)
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "succeeded"
    job = _row(job_id)
    assert job.state == JobState.succeeded and job.progress == 1.0 and job.attempts == 1
    assert {"fetch", "reconstruct", "assets", "photos", "tiles", "reconstruct.total"} <= set(
        job.timings
    )
    with capp.session_factory()() as session:
        model = session.get(Model, job.model_id)
    for name in (
        "model.glb",
        "thumbnail.png",
        "curvature.png",
        "curvature_coarse.png",
        "accessibility.png",
        "normals.png",
        "shading.json",
        "report.json",
        "photos/index.json",
        "gloss.json",
    ):
        assert name in model.assets, name
    assert sum(n.startswith("photos/") and n.endswith(".jpg") for n in model.assets) >= 3
    assert model.version == 1 and model.report["quality"]["tablet_pixels"] > 0
    # The tiles for streaming: recorded once, their stats in the report.
    assert {n for n in model.assets if n.startswith("tiles/")} == {
        "tiles/index.json",
        "tiles/files.json",
    }
    assert model.report["tiles"]["tiles_3d"] >= 1
    # The same message delivered again (acks_late after a crash before the ack).
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "succeeded"
    with capp.session_factory()() as session:
        assert session.scalar(select(func.count()).select_from(Model)) == 1
    assert _row(job_id).attempts == 1

    # A derive job (re)makes the assets of the scan's latest model, in place.
    with capp.session_factory()() as session:
        derive = jobs.create(session, scan=session.get(Scan, job.scan_id), kind=JobKind.derive)
        session.commit()
        derive_id = derive.id
    assert tasks.derive_assets.apply(args=[derive_id]).get() == "succeeded"
    derived = _row(derive_id)
    assert derived.state == JobState.succeeded and derived.model_id == model.id
    with capp.session_factory()() as session:
        assert session.scalar(select(func.count()).select_from(Model)) == 1
        assets = session.get(Model, model.id).assets
        assert "accessibility.png" in assets
        # Tiles rebuilt in place: the same tileset, still recorded once.
        assert "tiles/index.json" in assets and "tiles/3d/tileset.json" not in assets
    files = storage_from_settings(env).read_bytes(f"{model.storage_prefix}/tiles/files.json")
    assert "3d/tileset.json" in files.decode()


def test_a_job_running_with_a_live_heartbeat_is_left_alone(env):
    job_id = _scan_job(env)
    with capp.session_factory()() as session:
        job = session.get(Job, job_id)
        job.state, job.attempts, job.heartbeat_at = JobState.running, 1, datetime.now(UTC)
        session.commit()
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "busy"
    assert _row(job_id).attempts == 1


def test_a_bundle_that_cannot_be_read_fails_the_job_with_a_message(env):
    job_id = _scan_job(env)
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "failed"
    job = _row(job_id)
    assert job.state == JobState.failed
    assert job.error.startswith("reconstruction:") and "Traceback" not in job.error
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "failed"  # no second run


def test_only_named_transient_errors_are_retried():
    assert tasks.is_transient(StorageError("s3 down", status_code=503))
    assert tasks.is_transient(OperationalError("select", {}, Exception("gone")))
    assert tasks.is_transient(ConnectionError())
    assert not tasks.is_transient(ObjectNotFound("k"))
    assert not tasks.is_transient(StorageError("disk full", status_code=507))
    assert not tasks.is_transient(ValueError("bad bundle"))


def test_a_redelivery_after_a_kill_takes_over_at_once_despite_a_fresh_heartbeat(env):
    job_id = _scan_job(env)
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    owner = jobs.process_owner(child.pid)
    child.kill()
    child.wait(10)
    with capp.session_factory()() as session:
        job = session.get(Job, job_id)
        job.state, job.attempts, job.heartbeat_at = JobState.running, 1, datetime.now(UTC)
        job.claimed_by = owner  # the killed attempt's process
        session.commit()
    # Not 'busy': the job runs again (and fails cleanly: this bundle cannot be read).
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "failed"
    job = _row(job_id)
    assert job.attempts == 2 and job.claimed_by == jobs.process_owner()
    assert job.error.startswith("reconstruction:")


def test_a_transient_error_hands_the_job_back_to_the_queue_for_its_retry(env, monkeypatch):
    job_id = _scan_job(env)

    def unavailable(settings):
        raise StorageError("storage is restarting", status_code=503)

    monkeypatch.setattr(tasks, "storage_from_settings", unavailable)
    waits = []
    real_wait = jobs.wait_to_retry

    def recording_wait(session, *, job_id, attempt):
        waits.append((attempt, real_wait(session, job_id=job_id, attempt=attempt)))
        waits.append(_state(session, job_id))
        return waits[-2][1]

    monkeypatch.setattr(jobs, "wait_to_retry", recording_wait)
    monkeypatch.setattr(tasks, "MAX_RETRIES", 1)
    # Eager mode runs the retry at once: attempt 1 waits, attempt 2 is the last and fails.
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "failed"
    assert waits == [(1, True), (JobState.queued, jobs.WAITING_TO_RETRY)]
    job = _row(job_id)
    assert job.state == JobState.failed and job.attempts == 2
    assert "storage is restarting" in job.error


def _state(session, job_id):
    job = session.get(Job, job_id, populate_existing=True)
    return job.state, job.stage
