"""The job queue around the database: broker choice, Celery configuration, the sweeper.

The database is the source of truth for jobs; the broker only carries "run job N now".
Anything the broker loses (Redis restarted without persistence, a worker killed with
SIGKILL while it held a message) is found here by looking at the job rows:

- a job ``queued`` for longer than ``job_queued_stale_after_s`` without being picked up, or
- a job ``running`` whose heartbeat is older than ``job_stale_after_s``

is sent again (:func:`sweep`). Each re-send first *claims* the row with a conditional UPDATE
(``WHERE state = ... AND <timestamp> < cutoff``), so two sweepers never send the same job
twice in one period. A duplicate message is harmless anyway: the worker checks the row
before working (``worker.tasks``) and ``models.job_id`` is unique.

Embedded default: with no ``HAMMURABI_BROKER_URL`` the broker is kombu's SQLAlchemy
transport on ``<data_dir>/broker.sqlite`` (no server). No worker code is imported here.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from backend.jobs import TASK_BY_KIND, Dispatcher
from backend.tables import Job, JobState

log = logging.getLogger("backend.queue")

EMBEDDED_BROKER_FILE = "broker.sqlite"


def broker_url(settings: Any) -> str:
    """The configured broker, or the embedded SQLite broker in ``<data_dir>``."""
    if settings.broker_url:
        return settings.broker_url
    path = (Path(settings.data_dir) / EMBEDDED_BROKER_FILE).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    return f"sqla+sqlite:///{path}"


def is_embedded(url: str) -> bool:
    return url.startswith(("sqla+", "filesystem:", "memory:"))


def celery_config(settings: Any) -> dict[str, Any]:
    """Celery settings shared by every worker (``worker.celery_app``).

    acks_late + prefetch 1: a message is acknowledged only after its job is finished, and a
    worker holds one job at a time (long tasks; no job waits behind a busy worker). Results
    are not kept: the job row is the result.
    """
    url = broker_url(settings)
    hard_s = float(settings.job_time_limit_s)
    config: dict[str, Any] = {
        "broker_url": url,
        "broker_connection_retry_on_startup": True,
        "task_default_queue": settings.job_queue,
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        "task_ignore_result": True,
        "task_time_limit": hard_s,
        # The soft limit raises inside the task, which records a clear failure first.
        "task_soft_time_limit": max(1.0, hard_s - min(60.0, 0.1 * hard_s)),
        "worker_hijack_root_logger": False,
        "worker_max_tasks_per_child": 50,  # numerical code: return memory to the system
    }
    if url.startswith("redis"):
        # Redis re-delivers unacked messages after the visibility timeout: keep it beyond the
        # time limit so a long job is never run twice; dead workers are the sweeper's job.
        config["broker_transport_options"] = {"visibility_timeout": hard_s + 600}
    if is_embedded(url):
        # The embedded transports have no broadcast: no remote control or events.
        config["worker_enable_remote_control"] = False
        config["worker_send_task_events"] = False
    return config


@dataclass(frozen=True)
class SweepResult:
    requeued_queued: list[int]
    requeued_stale: list[int]

    @property
    def count(self) -> int:
        return len(self.requeued_queued) + len(self.requeued_stale)


def _now() -> datetime:
    return datetime.now(UTC)


def sweep(
    session: Session,
    dispatcher: Dispatcher,
    *,
    queued_stale_after_s: float,
    running_stale_after_s: float,
    now: datetime | None = None,
    limit: int = 500,
) -> SweepResult:
    """Send again the jobs the broker lost; returns their ids. Commits each claim.

    A running job with a stale heartbeat goes back to ``queued`` (its worker is gone); the
    redelivered task starts it again (``attempts`` + 1). A send that fails leaves the row
    claimed: it is tried again after the next stale period.
    """
    if queued_stale_after_s <= 0 or running_stale_after_s <= 0:
        raise ValueError("queued_stale_after_s and running_stale_after_s must be > 0")
    now = now or _now()
    queued_cutoff = now - timedelta(seconds=queued_stale_after_s)
    running_cutoff = now - timedelta(seconds=running_stale_after_s)
    since = func.coalesce(Job.enqueued_at, Job.created_at)
    beat = func.coalesce(Job.heartbeat_at, Job.started_at, Job.created_at)

    lost = session.scalars(
        select(Job.id)
        .where(Job.state == JobState.queued, since < queued_cutoff)
        .order_by(Job.id)
        .limit(limit)
    ).all()
    stale = session.scalars(
        select(Job.id)
        .where(Job.state == JobState.running, beat < running_cutoff)
        .order_by(Job.id)
        .limit(limit)
    ).all()
    session.rollback()  # end the read transaction before the claims (SQLite locks)

    requeued_queued = [
        job_id
        for job_id in lost
        if _claim(session, job_id, JobState.queued, since < queued_cutoff, now)
        and _send(session, dispatcher, job_id)
    ]
    requeued_stale = [
        job_id
        for job_id in stale
        if _claim(session, job_id, JobState.running, beat < running_cutoff, now)
        and _send(session, dispatcher, job_id)
    ]
    if requeued_queued or requeued_stale:
        log.warning(
            "sweeper: re-sent lost queued jobs %s and stale running jobs %s",
            requeued_queued,
            requeued_stale,
        )
    return SweepResult(requeued_queued, requeued_stale)


def _claim(session: Session, job_id: int, state: JobState, condition, now: datetime) -> bool:
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == state, condition)
        .values(state=JobState.queued, enqueued_at=now, stage=None)
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


def _send(session: Session, dispatcher: Dispatcher, job_id: int) -> bool:
    job = session.get(Job, job_id, populate_existing=True)
    if job is None:
        return False
    task_id = f"job-{job.id}-attempt-{job.attempts + 1}-resend-{_now().timestamp():.0f}"
    try:
        dispatcher.send_task(TASK_BY_KIND[job.kind], args=[job.id], task_id=task_id)
    except Exception:  # broker down: the next sweep tries again
        log.exception("sweeper: could not re-send job %s", job_id)
        return False
    finally:
        session.rollback()
    return True


def heartbeat(session: Session, *, job_id: int, attempt: int) -> bool:
    """Refresh the heartbeat of ``job_id`` if it is still running as ``attempt``.

    Returns False when the job is no longer ours (finished, or taken over after we were
    thought dead): the caller should stop working on it.
    """
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.running, Job.attempts == attempt)
        .values(heartbeat_at=_now())
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


def claim(session: Session, *, job_id: int, running_stale_after_s: float) -> int | None:
    """Start ``job_id`` for this worker; return its attempt number, or None if not ours.

    One conditional UPDATE (atomic on SQLite and PostgreSQL): a queued job, or a running one
    whose heartbeat is older than ``running_stale_after_s`` (its worker died), becomes
    running with ``attempts + 1``. A job that is finished, or running with a live
    heartbeat elsewhere, is left alone: a redelivered or duplicated message does no work.
    """
    now = _now()
    cutoff = now - timedelta(seconds=running_stale_after_s)
    beat = func.coalesce(Job.heartbeat_at, Job.started_at, Job.created_at)
    result = session.execute(
        update(Job)
        .where(
            Job.id == job_id,
            (Job.state == JobState.queued) | ((Job.state == JobState.running) & (beat < cutoff)),
        )
        .values(
            state=JobState.running,
            attempts=Job.attempts + 1,
            started_at=now,
            heartbeat_at=now,
            progress=0.0,
            stage="starting",
            error=None,
        )
        .execution_options(synchronize_session=False)
    )
    session.commit()
    if result.rowcount != 1:
        return None
    return session.scalar(select(Job.attempts).where(Job.id == job_id))


class Sweeper:
    """Runs :func:`sweep` now and then every ``interval_s`` in a daemon thread."""

    def __init__(self, factory: sessionmaker[Session], dispatcher: Dispatcher, settings: Any):
        self.factory = factory
        self.dispatcher = dispatcher
        self.interval_s = float(settings.job_sweep_interval_s)
        self.queued_stale_after_s = float(settings.job_queued_stale_after_s)
        self.running_stale_after_s = float(settings.job_stale_after_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def run_once(self) -> SweepResult | None:
        try:
            with self.factory() as session:
                return sweep(
                    session,
                    self.dispatcher,
                    queued_stale_after_s=self.queued_stale_after_s,
                    running_stale_after_s=self.running_stale_after_s,
                )
        except Exception:  # a database hiccup must not kill the sweeper thread
            log.exception("sweeper: sweep failed")
            return None

    def _loop(self) -> None:
        self.run_once()
        while not self._stop.wait(self.interval_s):
            self.run_once()

    def start(self) -> Sweeper:
        self._thread = threading.Thread(target=self._loop, name="job-sweeper", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
