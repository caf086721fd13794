"""worker.tasks starts the tablet's registration by itself (in-process, fake reconstruction):
one register job once two faces have models, none for one face, none twice for redelivered
or duplicated completions, a new one for a face model newer than the last registration, and
one for a set of faces uploaded together, after its last face (succeeded or failed)."""

from __future__ import annotations

import json

import pytest
from sqlalchemy import select

from backend import jobs
from backend.db import migrate
from backend.jobs import claim
from backend.settings import Settings
from backend.storage import storage_from_settings
from backend.tables import Job, JobKind, JobState, Scan, Tablet
from worker import celery_app as capp
from worker import tasks


class Down:
    def send_task(self, name, *, args, task_id):
        raise ConnectionError("broker down")


@pytest.fixture
def env(tmp_path, monkeypatch):
    settings = Settings(data_dir=tmp_path / "data", _env_file=None, job_stale_after_s=30)
    migrate(settings.resolved_database_url)
    previous = capp.settings
    capp.configure(settings)
    sent = jobs.RecordingDispatcher()
    monkeypatch.setattr(tasks, "dispatcher", lambda: sent)

    def fake_reconstruct(beat, job):
        # The real store step (mark_succeeded) on a minimal model directory: the trigger
        # depends on the committed model row, not on the numerical pipeline.
        model_dir = tmp_path / f"model-{job.id}"
        model_dir.mkdir()
        (model_dir / "model.glb").write_bytes(b"glTF")
        (model_dir / "report.json").write_text(json.dumps({"job": job.id}))
        tasks._store(job.id, model_dir, storage_from_settings(capp.settings))
        return "succeeded"

    monkeypatch.setattr(tasks, "_reconstruct", fake_reconstruct)
    yield sent
    capp.configure(previous)


def _tablet() -> int:
    with capp.session_factory()() as session:
        tablet = Tablet(designation="trigger test")
        session.add(tablet)
        session.commit()
        return tablet.id


def _scan_job(tablet_id: int, face: str) -> int:
    with capp.session_factory()() as session:
        scan = Scan(
            tablet_id=tablet_id,
            face=face,
            bundle_key=f"scans/{tablet_id}/{face}",
            bundle_sha256="0" * 64,
            size_bytes=1,
        )
        session.add(scan)
        session.flush()
        job = jobs.create(session, scan=scan)
        session.commit()
        return job.id


def _reconstructed(tablet_id: int, face: str) -> int:
    job_id = _scan_job(tablet_id, face)
    assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "succeeded"
    return job_id


def _register_jobs(tablet_id: int) -> list[Job]:
    with capp.session_factory()() as session:
        return list(
            session.scalars(
                select(Job)
                .where(Job.tablet_id == tablet_id, Job.kind == JobKind.register)
                .order_by(Job.id)
            )
        )


def _finish(job_id: int) -> None:
    """The register job ran (claimed now) and succeeded."""
    with capp.session_factory()() as session:
        assert claim(session, job_id=job_id, running_stale_after_s=30) == 1
    tasks._finish_noop(job_id)


def test_two_faces_queue_exactly_one_register_job_and_redelivery_adds_none(env):
    tablet_id = _tablet()
    first = _reconstructed(tablet_id, "obverse")
    assert _register_jobs(tablet_id) == [] and env.sent == []  # one face: nothing to register

    second = _reconstructed(tablet_id, "reverse")
    (register,) = _register_jobs(tablet_id)
    assert register.state == JobState.queued and register.scan_id is None
    assert register.enqueued_at is not None
    assert env.sent == [
        ("worker.tasks.register_tablet", [register.id], f"job-{register.id}-attempt-1")
    ]

    # Redelivered messages of both reconstructions, and a third face while it is queued.
    for job_id in (first, second, second):
        assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "succeeded"
    _reconstructed(tablet_id, "top")
    assert [j.id for j in _register_jobs(tablet_id)] == [register.id] and len(env.sent) == 1


def test_one_face_even_rescanned_queues_no_register_job(env):
    tablet_id = _tablet()
    _reconstructed(tablet_id, "obverse")
    _reconstructed(tablet_id, "obverse")  # a re-scan: two scans, still one face
    assert _register_jobs(tablet_id) == [] and env.sent == []


def test_a_face_model_newer_than_the_last_registration_queues_a_new_one(env):
    tablet_id = _tablet()
    _reconstructed(tablet_id, "obverse")
    second = _reconstructed(tablet_id, "reverse")
    (register,) = _register_jobs(tablet_id)
    _finish(register.id)
    # Finished and nothing new: a redelivered completion adds nothing.
    assert tasks.reconstruct_scan.apply(args=[second]).get() == "succeeded"
    assert len(_register_jobs(tablet_id)) == 1

    _reconstructed(tablet_id, "obverse")  # a re-scan after the registration
    older, newer = _register_jobs(tablet_id)
    assert older.id == register.id and newer.state == JobState.queued
    assert [args for _, args, _ in env.sent] == [[register.id], [newer.id]]


def test_a_face_finished_while_registration_runs_is_registered_after_it(env, monkeypatch):
    tablet_id = _tablet()
    _reconstructed(tablet_id, "obverse")
    _reconstructed(tablet_id, "reverse")
    (register,) = _register_jobs(tablet_id)

    def fake_register(beat, job):
        # A third face is stored after this registration read the models: not in it.
        _reconstructed(tablet_id, "top")
        assert len(_register_jobs(tablet_id)) == 1  # one is running: none added meanwhile
        return tasks._finish_noop(job.id)

    monkeypatch.setattr(tasks, "_register", fake_register)
    assert tasks.register_tablet.apply(args=[register.id]).get() == "succeeded"
    first, follow_up = _register_jobs(tablet_id)
    assert first.state == JobState.succeeded and follow_up.state == JobState.queued
    # The redelivered register message finds its job finished and the follow-up queued.
    assert tasks.register_tablet.apply(args=[register.id]).get() == "succeeded"
    assert len(_register_jobs(tablet_id)) == 2


def test_a_broker_that_is_down_leaves_the_register_job_queued_for_the_sweeper(env, monkeypatch):
    monkeypatch.setattr(tasks, "dispatcher", Down)
    tablet_id = _tablet()
    _reconstructed(tablet_id, "obverse")
    job_id = _reconstructed(tablet_id, "reverse")  # the reconstruction itself still succeeds
    (register,) = _register_jobs(tablet_id)
    assert register.state == JobState.queued and register.enqueued_at is None
    with capp.session_factory()() as session:
        assert session.get(Job, job_id).state == JobState.succeeded


def test_a_set_of_faces_uploaded_together_is_registered_once_after_its_last_face(env):
    tablet_id = _tablet()
    faces = ("obverse", "top", "bottom", "left", "right", "reverse")
    job_ids = [_scan_job(tablet_id, face) for face in faces]  # all six uploaded, queued
    for job_id in job_ids[:-1]:
        assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "succeeded"
        assert _register_jobs(tablet_id) == [] and env.sent == []  # faces still pending
    assert tasks.reconstruct_scan.apply(args=[job_ids[-1]]).get() == "succeeded"
    (register,) = _register_jobs(tablet_id)
    assert register.state == JobState.queued and len(env.sent) == 1


def test_a_failed_last_face_still_starts_the_registration_of_the_others(env, monkeypatch):
    tablet_id = _tablet()
    first, second, last = (_scan_job(tablet_id, f) for f in ("obverse", "reverse", "top"))
    for job_id in (first, second):
        assert tasks.reconstruct_scan.apply(args=[job_id]).get() == "succeeded"
    assert _register_jobs(tablet_id) == []

    def broken(beat, job):
        tasks._fail(job.id, "the bundle's fringe frames are unreadable")
        return "failed"

    monkeypatch.setattr(tasks, "_reconstruct", broken)
    assert tasks.reconstruct_scan.apply(args=[last]).get() == "failed"
    (register,) = _register_jobs(tablet_id)
    assert register.state == JobState.queued
