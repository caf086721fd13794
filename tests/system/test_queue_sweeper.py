"""backend.queue: the sweeper re-sends lost and stale jobs exactly once per period; claims."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from backend import jobs
from backend.db import make_engine, make_sessionmaker, migrate
from backend.jobs import RecordingDispatcher
from backend.queue import broker_url, celery_config, claim, heartbeat, sweep
from backend.settings import Settings
from backend.tables import Job, JobKind, JobState, Scan, Tablet


@pytest.fixture
def factory(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    migrate(url)
    engine = make_engine(url)
    yield make_sessionmaker(engine)
    engine.dispose()


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
