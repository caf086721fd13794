"""backend.sweeper: the sweeper re-sends lost and stale jobs exactly once per period; claims
(backend.jobs); jobs awaiting dispatch (backend.dispatch); the scheduled expiry."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import uuid
from datetime import UTC, datetime, timedelta

import pytest

from backend import dispatch, jobs, sweeper
from backend.db import make_engine, make_sessionmaker, migrate
from backend.jobs import RecordingDispatcher, claim, heartbeat
from backend.queue import broker_url, celery_config
from backend.settings import Settings
from backend.sweeper import sweep
from backend.tables import Job, JobKind, JobState, Scan, Tablet, Upload
from backend.uploads import part_path


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def factory(request, tmp_path):
    """A migrated database: a SQLite file, or a fresh PostgreSQL database (loopback)."""
    if request.param == "sqlite":
        url, drop = f"sqlite:///{tmp_path / 'db.sqlite'}", None
    else:
        import psycopg

        name = f"hammurabi_sweeper_{uuid.uuid4().hex[:12]}"
        admin = "host=127.0.0.1 port=5432 user=postgres dbname=postgres"
        with psycopg.connect(admin, autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        url = f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"

        def drop():
            with psycopg.connect(admin, autocommit=True) as conn:
                conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')

    try:
        migrate(url)
        engine = make_engine(url)
        yield make_sessionmaker(engine)
        engine.dispose()
    finally:
        if drop is not None:
            drop()


def _job(factory, *, state=JobState.queued, age_s=0.0, beat_age_s=None, kind=JobKind.reconstruct):
    with factory() as session:
        tablet = Tablet(designation="t")
        session.add(tablet)
        session.flush()
        scan = Scan(
            tablet_id=tablet.id,
            face="obverse",
            bundle_key="k",
            bundle_sha256="0" * 64,
            size_bytes=1,
        )
        session.add(scan)
        session.flush()
        job = jobs.create(session, scan=scan, kind=kind)
        then = datetime.now(UTC) - timedelta(seconds=age_s)
        job.state, job.enqueued_at, job.created_at = state, then, then
        if beat_age_s is not None:
            job.attempts = 1
            job.heartbeat_at = datetime.now(UTC) - timedelta(seconds=beat_age_s)
        session.commit()
        return job.id


def _sweep(factory, dispatcher):
    with factory() as session:
        return sweep(session, dispatcher, queued_stale_after_s=60, running_stale_after_s=30)


def test_lost_queued_and_stale_running_jobs_are_resent_once(factory):
    lost = _job(factory, age_s=120)
    fresh = _job(factory, age_s=1)
    stale = _job(factory, state=JobState.running, age_s=300, beat_age_s=100)
    alive = _job(factory, state=JobState.running, age_s=300, beat_age_s=2)
    done = _job(factory, state=JobState.succeeded, age_s=300)
    register = _job(factory, age_s=120, kind=JobKind.register)
    dispatcher = RecordingDispatcher()
    result = _sweep(factory, dispatcher)
    assert result.requeued_queued == [lost, register]
    assert result.requeued_stale == [stale]
    sent = {(name, args[0]) for name, args, _ in dispatcher.sent}
    assert sent == {
        (jobs.RECONSTRUCT_TASK, lost),
        ("worker.tasks.register_tablet", register),
        (jobs.RECONSTRUCT_TASK, stale),
    }
    with factory() as session:
        assert session.get(Job, stale).state == JobState.queued
        assert session.get(Job, alive).state == JobState.running
        assert session.get(Job, fresh).state == JobState.queued
        assert session.get(Job, done).state == JobState.succeeded
    # The claims moved the timestamps: a second sweeper right after sends nothing.
    again = RecordingDispatcher()
    assert _sweep(factory, again).count == 0 and again.sent == []


def test_a_failed_send_is_retried_by_a_later_sweep(factory):
    lost = _job(factory, age_s=120)

    class Down:
        def send_task(self, name, *, args, task_id):
            raise ConnectionError("broker down")

    assert _sweep(factory, Down()).count == 0
    later = datetime.now(UTC) + timedelta(seconds=61)
    dispatcher = RecordingDispatcher()
    with factory() as session:
        result = sweep(
            session, dispatcher, queued_stale_after_s=60, running_stale_after_s=30, now=later
        )
    assert result.requeued_queued == [lost]


def test_claim_takes_queued_or_stale_jobs_once_and_heartbeat_tracks_the_owner(factory):
    queued = _job(factory)
    with factory() as session:
        assert claim(session, job_id=queued, running_stale_after_s=30) == 1
        # A duplicate message: running with a live heartbeat, not ours.
        assert claim(session, job_id=queued, running_stale_after_s=30) is None
        assert heartbeat(session, job_id=queued, attempt=1)
        assert not heartbeat(session, job_id=queued, attempt=2)
    stale = _job(factory, state=JobState.running, age_s=300, beat_age_s=100)
    with factory() as session:
        assert claim(session, job_id=stale, running_stale_after_s=30) == 2
        assert not heartbeat(session, job_id=stale, attempt=1)  # the old owner must stop
    done = _job(factory, state=JobState.succeeded)
    with factory() as session:
        assert claim(session, job_id=done, running_stale_after_s=30) is None


def test_embedded_broker_is_the_default(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", _env_file=None)
    assert broker_url(settings) == f"sqla+sqlite:///{(tmp_path / 'data' / 'broker.sqlite')}"
    config = celery_config(settings)
    assert config["task_acks_late"] and config["worker_prefetch_multiplier"] == 1
    assert config["task_soft_time_limit"] < config["task_time_limit"]
    redis = Settings(data_dir=tmp_path, broker_url="redis://r:6379/0", _env_file=None)
    assert celery_config(redis)["broker_transport_options"]["visibility_timeout"] > (
        redis.job_time_limit_s
    )


class Down:
    def __init__(self) -> None:
        self.calls = 0

    def send_task(self, name, *, args, task_id):
        self.calls += 1
        raise ConnectionError("broker down")


def _row(factory, job_id) -> Job:
    with factory() as session:
        return session.get(Job, job_id)


def test_an_outage_leaves_the_job_queued_and_the_dispatcher_sends_it_with_backoff(factory):
    job_id = _job(factory)
    down = Down()
    with factory() as session:
        job = dispatch.dispatch(session, job_id=job_id, dispatcher=down, backoff_max_s=4)
    assert job.state == JobState.queued and job.stage == jobs.AWAITING_DISPATCH
    row = _row(factory, job_id)
    assert row.enqueued_at is None and row.dispatch_failures == 1 and row.error is None
    not_yet = row.dispatch_after - timedelta(seconds=0.5)
    # Not due yet: nothing is tried; the lost-job path does not touch it either.
    with factory() as session:
        result = sweep(
            session, down, queued_stale_after_s=0.001, running_stale_after_s=30, now=not_yet
        )
    assert result.count == 0 and down.calls == 1  # only the first send
    # Due, broker still down: the wait doubles, up to the maximum.
    waits = []
    for _ in range(4):
        due = _row(factory, job_id).dispatch_after
        before = jobs.now_utc()
        with factory() as session:
            assert dispatch.dispatch_due(session, down, backoff_max_s=4, now=due) == []
        after = jobs.now_utc()
        # The next send is due a backoff after this (failed) one, which happened between
        # `before` and `after` (bounds, not a rounding of the clock: on a loaded machine the
        # send and the reading can be a second apart).
        next_send = _row(factory, job_id).dispatch_after.replace(tzinfo=UTC)  # SQLite: naive
        lo, hi = (next_send - after).total_seconds(), (next_send - before).total_seconds()
        fits = [w for w in (1, 2, 4, 8) if lo - 0.01 <= w <= hi + 0.01]
        waits.append(fits[0] if len(fits) == 1 else (lo, hi))
    assert waits == [2, 4, 4, 4] and _row(factory, job_id).dispatch_failures == 5
    assert _row(factory, job_id).state == JobState.queued
    # The broker is back: the next due sweep sends it and clears the pending dispatch.
    up = RecordingDispatcher()
    due = _row(factory, job_id).dispatch_after
    with factory() as session:
        result = sweep(session, up, queued_stale_after_s=600, running_stale_after_s=30, now=due)
    assert result.dispatched == [job_id]
    assert up.sent == [(jobs.RECONSTRUCT_TASK, [job_id], f"job-{job_id}-attempt-1")]
    row = _row(factory, job_id)
    assert row.state == JobState.queued and row.dispatch_after is None
    assert row.dispatch_failures == 0 and row.enqueued_at is not None and row.stage is None
    assert dispatch.backoff_s(0, max_s=60) == 0 and dispatch.backoff_s(3, max_s=60) == 4


def _dead_owner() -> str:
    """The owner string of a process that has exited (and been reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        owner = jobs.process_owner(child.pid)
    finally:
        child.kill()
        child.wait(10)
    return owner


def test_a_redelivery_takes_over_at_once_from_a_killed_owner_but_not_from_a_live_one(factory):
    live = _job(factory, state=JobState.running, beat_age_s=0.5)
    dead = _job(factory, state=JobState.running, beat_age_s=0.5)
    owner = _dead_owner()
    assert jobs.owner_is_dead(owner) and not jobs.owner_is_dead(jobs.process_owner())
    assert not jobs.owner_is_dead("other-host/1/1/1") and not jobs.owner_is_dead(None)
    with factory() as session:
        session.get(Job, live).claimed_by = jobs.process_owner()
        session.get(Job, dead).claimed_by = owner
        session.commit()
    with factory() as session:
        assert claim(session, job_id=live, running_stale_after_s=30) is None  # 'busy'
        assert claim(session, job_id=dead, running_stale_after_s=30) == 2
        assert claim(session, job_id=dead, running_stale_after_s=30) is None  # now live: ours
    row = _row(factory, dead)
    assert row.state == JobState.running and row.claimed_by == jobs.process_owner()


def test_the_sweeper_requeues_a_killed_owners_job_without_waiting_for_its_heartbeat(factory):
    job_id = _job(factory, state=JobState.running, beat_age_s=0.5)
    with factory() as session:
        session.get(Job, job_id).claimed_by = _dead_owner()
        session.commit()
    sent = RecordingDispatcher()
    with factory() as session:
        result = sweep(session, sent, queued_stale_after_s=600, running_stale_after_s=600)
    assert result.requeued_stale == [job_id]
    assert [args for _, args, _ in sent.sent] == [[job_id]]
    assert _row(factory, job_id).state == JobState.queued


def test_concurrent_claims_of_one_job_have_exactly_one_winner(factory):
    job_id = _job(factory)
    barrier = threading.Barrier(6)
    winners = []

    def contender():
        with factory() as session:
            barrier.wait()
            attempt = claim(session, job_id=job_id, running_stale_after_s=30)
            if attempt is not None:
                winners.append(attempt)

    threads = [threading.Thread(target=contender) for _ in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert winners == [1]
    assert _row(factory, job_id).attempts == 1


def test_only_the_work_folders_of_dead_attempts_are_removed(tmp_path):
    root = tmp_path / "tmp"
    root.mkdir()
    mine = jobs.make_work_folder(root, job_id=1, attempt=1)
    killed = jobs.make_work_folder(root, job_id=2, attempt=1, kind="derive")
    (killed / jobs.OWNER_FILE).write_text(_dead_owner())
    (killed / "bundle.zip").write_bytes(bytes(1000))
    elsewhere = jobs.make_work_folder(root, job_id=3, attempt=1)
    (elsewhere / jobs.OWNER_FILE).write_text("another-host/4026531836/1234/99")
    old_unowned = root / "hammurabi-register-4-abc"
    old_unowned.mkdir()
    os.utime(old_unowned, (time.time() - 7200, time.time() - 7200))
    fresh_unowned = root / "hammurabi-job-5-xyz"
    fresh_unowned.mkdir()
    unrelated = root / "not-ours"
    unrelated.mkdir()
    removed = jobs.remove_dead_work_folders(root, unowned_older_than_s=3600)
    assert sorted(removed) == sorted([killed, old_unowned])
    assert mine.is_dir() and elsewhere.is_dir() and fresh_unowned.is_dir() and unrelated.is_dir()
    assert not killed.exists() and not old_unowned.exists()
    with pytest.raises(ValueError, match="kind"):
        jobs.make_work_folder(root, job_id=1, attempt=1, kind="../x")


def test_the_sweeper_thread_expires_abandoned_uploads_and_dead_folders_on_its_schedule(
    factory, tmp_path, monkeypatch
):
    settings = Settings(
        data_dir=tmp_path / "data",
        _env_file=None,
        job_sweep_interval_s=0.1,
        maintenance_interval_s=0.3,
        upload_expire_after_s=60,
    )
    uploads_dir = sweeper.uploads_dir(settings)
    uploads_dir.mkdir(parents=True)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.setattr(jobs, "work_root", lambda: work)
    with factory() as session:
        tablet = Tablet(designation="uploads")
        session.add(tablet)
        session.flush()
        old = datetime.now(UTC) - timedelta(seconds=120)
        for upload_id, when in ((str(uuid.uuid4()), old), (str(uuid.uuid4()), datetime.now(UTC))):
            session.add(
                Upload(
                    id=upload_id,
                    tablet_id=tablet.id,
                    filename="b.zip",
                    size_bytes=10,
                    created_at=when,
                    updated_at=when,
                )
            )
            part_path(uploads_dir, upload_id).write_bytes(bytes(10))
        session.commit()
    # updated_at is set on flush by onupdate only for updates: check what was stored.
    with factory() as session:
        assert session.query(Upload).count() == 2
    killed = jobs.make_work_folder(work, job_id=9, attempt=1)
    (killed / jobs.OWNER_FILE).write_text(_dead_owner())

    runner = sweeper.Sweeper(factory, RecordingDispatcher(), settings).start()
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with factory() as session:
                if session.query(Upload).count() == 1 and not killed.exists():
                    break
            time.sleep(0.05)
    finally:
        runner.stop()
    with factory() as session:
        (left,) = session.query(Upload).all()
    assert left.updated_at.replace(tzinfo=UTC) > datetime.now(UTC) - timedelta(seconds=60)
    assert [p.stem for p in uploads_dir.glob("*.part")] == [left.id]
    assert not killed.exists()


def test_only_the_services_sweeper_expires_uploads(factory, tmp_path):
    settings = Settings(data_dir=tmp_path / "data", _env_file=None, upload_expire_after_s=60)
    sweeper.uploads_dir(settings).mkdir(parents=True)
    with factory() as session:
        tablet = Tablet(designation="uploads")
        session.add(tablet)
        session.flush()
        old = datetime.now(UTC) - timedelta(seconds=120)
        session.add(
            Upload(
                id=str(uuid.uuid4()),
                tablet_id=tablet.id,
                filename="b.zip",
                size_bytes=10,
                created_at=old,
                updated_at=old,
            )
        )
        session.commit()
    workers = sweeper.Sweeper(factory, RecordingDispatcher(), settings, expire_uploads=False)
    assert workers.maintain_once().expired_uploads == 0
    service = sweeper.Sweeper(factory, RecordingDispatcher(), settings)
    assert service.maintain_once().expired_uploads == 1
    with factory() as session:
        assert session.query(Upload).count() == 0


def test_a_claim_timeout_shorter_than_two_heartbeats_is_refused(tmp_path):
    with pytest.raises(ValueError, match="at least two heartbeats"):
        Settings(data_dir=tmp_path, _env_file=None, job_heartbeat_interval_s=5, job_stale_after_s=9)
    defaults = Settings(data_dir=tmp_path, _env_file=None)
    # Recovery in seconds: a dead attempt is taken over after 3 missed heartbeats at most.
    assert defaults.job_stale_after_s == 3 * defaults.job_heartbeat_interval_s == 15


def test_jobs_failed_by_an_old_outage_are_queued_again_by_the_migration(tmp_path):
    from sqlalchemy import text

    url = f"sqlite:///{tmp_path / 'old.sqlite'}"
    migrate(url, "0004_search")
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(
            text(
                "INSERT INTO tablets (id, designation, is_public, has_3d, extra, created_at,"
                " updated_at) VALUES (1, 't', 0, 0, '{}', CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
            )
        )
        for job_id, error in ((1, "could not reach the job queue: OperationalError"), (2, "bad")):
            conn.execute(
                text(
                    "INSERT INTO jobs (id, tablet_id, kind, state, progress, timings, error,"
                    " attempts, created_at, finished_at) VALUES (:id, 1, 'reconstruct',"
                    " 'failed', 0, '{}', :error, 0, CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
                ),
                {"id": job_id, "error": error},
            )
    migrate(url)
    factory = make_sessionmaker(engine)
    with factory() as session:
        lost, bad = session.get(Job, 1), session.get(Job, 2)
        assert lost.state == JobState.queued and lost.error is None
        assert lost.stage == jobs.AWAITING_DISPATCH and lost.finished_at is None
        assert bad.state == JobState.failed and bad.error == "bad"
    sent = RecordingDispatcher()
    with factory() as session:
        later = datetime.now(UTC) + timedelta(seconds=5)
        assert dispatch.dispatch_due(session, sent, backoff_max_s=60, now=later) == [1]
    engine.dispose()
