"""The sweeper: finds the jobs the broker or a worker lost, and does the periodic cleanup.

The database is the source of truth for jobs; the broker only carries "run job N now".
Every ``job_sweep_interval_s`` (:func:`sweep`):

- jobs *awaiting dispatch* (the broker was down when they were sent) are sent once their
  backoff has passed (``backend.dispatch.dispatch_due``);
- a job ``running`` whose owner process is provably dead (same host: a kill -9) or whose
  heartbeat is older than ``job_stale_after_s`` goes back to ``queued`` and is re-sent;
- a job ``queued`` (sent) for longer than ``job_queued_stale_after_s`` without being picked
  up (the broker lost the message, e.g. Redis restarted without persistence) is re-sent.

Every ``maintenance_interval_s`` (:func:`maintain`): uploads left open for
``upload_expire_after_s`` are deleted with their part files (``backend.uploads.expire_uploads``;
by the service's sweeper only, which holds the part files) and the work folders of dead
attempts are removed (``backend.jobs.remove_dead_work_folders``).

Schedule: this is a plain loop (:class:`Sweeper`, a daemon thread), not Celery beat, so the
embedded broker needs nothing more. It runs in every worker process (started when the worker
is ready, ``worker.celery_app``) and in ``hammurabi serve``; several sweepers are safe: each
re-send or dispatch first wins a compare-and-set on the job row.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from backend import dispatch, jobs, uploads
from backend.queue import Dispatcher
from backend.tables import Job, JobState

log = logging.getLogger("backend.sweeper")


@dataclass(frozen=True)
class SweepResult:
    requeued_queued: list[int]
    requeued_stale: list[int]
    dispatched: list[int] = field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.requeued_queued) + len(self.requeued_stale) + len(self.dispatched)


def sweep(
    session: Session,
    dispatcher: Dispatcher,
    *,
    queued_stale_after_s: float,
    running_stale_after_s: float,
    backoff_max_s: float = 60.0,
    now: datetime | None = None,
    limit: int = 500,
) -> SweepResult:
    """Send the jobs awaiting dispatch, and send again the jobs the broker or a worker lost.

    A send that fails leaves the job awaiting dispatch (``backend.dispatch``): the next
    sweeps retry it with backoff; it is never failed for an outage.
    """
    if queued_stale_after_s <= 0 or running_stale_after_s <= 0:
        raise ValueError("queued_stale_after_s and running_stale_after_s must be > 0")
    now = now or jobs.now_utc()
    dispatched = dispatch.dispatch_due(session, dispatcher, backoff_max_s=backoff_max_s, now=now)
    queued_cutoff = now - timedelta(seconds=queued_stale_after_s)
    running_cutoff = now - timedelta(seconds=running_stale_after_s)
    since = func.coalesce(Job.enqueued_at, Job.created_at)
    beat = func.coalesce(Job.heartbeat_at, Job.started_at, Job.created_at)

    lost = session.scalars(
        select(Job.id)
        .where(Job.state == JobState.queued, Job.dispatch_after.is_(None), since < queued_cutoff)
        .order_by(Job.id)
        .limit(limit)
    ).all()
    running = session.execute(
        select(Job.id, Job.attempts, Job.claimed_by, beat < running_cutoff)
        .where(Job.state == JobState.running)
        .order_by(Job.id)
        .limit(limit)
    ).all()
    session.rollback()  # end the read transaction before the claims (SQLite locks)

    def send(job_id: int) -> bool:
        return dispatch.resend(
            session, job_id=job_id, dispatcher=dispatcher, backoff_max_s=backoff_max_s
        )

    requeued_queued = [
        job_id
        for job_id in lost
        if jobs.requeue_lost(session, job_id=job_id, cutoff=queued_cutoff, now=now) and send(job_id)
    ]
    requeued_stale = []
    for job_id, attempt, owner, is_stale in running:
        if is_stale:
            cutoff = running_cutoff
        elif jobs.owner_is_dead(owner):
            cutoff = None  # killed on this host: no need to wait for the heartbeat to age
        else:
            continue
        if jobs.requeue_stale(session, job_id=job_id, attempt=attempt, cutoff=cutoff, now=now):
            send(job_id)  # a failed send leaves it awaiting dispatch: still recovered
            requeued_stale.append(job_id)
    if requeued_stale:
        # The dead attempts' work folders on this host go with them (kill -9 leaves them).
        jobs.remove_dead_work_folders(jobs.work_root(), unowned_older_than_s=float("inf"))
    if requeued_queued or requeued_stale:
        log.warning(
            "sweeper: re-sent lost queued jobs %s and jobs of dead workers %s",
            requeued_queued,
            requeued_stale,
        )
    return SweepResult(requeued_queued, requeued_stale, dispatched)


@dataclass(frozen=True)
class MaintenanceResult:
    expired_uploads: int
    removed_folders: list[Path]


def maintain(
    session: Session,
    *,
    uploads_dir: Path | None,
    upload_older_than: timedelta,
    work_root: Path,
    unowned_folder_older_than_s: float,
) -> MaintenanceResult:
    """Expire abandoned uploads (committed; skipped when ``uploads_dir`` is None: only the
    process that holds the part files expires them) and remove the work folders of dead
    attempts."""
    expired = 0
    if uploads_dir is not None:
        expired = uploads.expire_uploads(
            session, uploads_dir=uploads_dir, older_than=upload_older_than
        )
        session.commit()
    removed = jobs.remove_dead_work_folders(
        work_root, unowned_older_than_s=unowned_folder_older_than_s
    )
    if expired:
        log.warning("sweeper: expired %d abandoned uploads", expired)
    return MaintenanceResult(expired, removed)


def uploads_dir(settings: Any) -> Path:
    """Where the part files of uploads are (``backend.api.uploads`` writes them there)."""
    return Path(settings.data_dir) / "uploads"


class Sweeper:
    """Runs :func:`sweep` now and every ``job_sweep_interval_s``, and :func:`maintain` now
    and every ``maintenance_interval_s``, in a daemon thread."""

    def __init__(
        self,
        factory: sessionmaker[Session],
        dispatcher: Dispatcher,
        settings: Any,
        *,
        maintenance: bool = True,
        expire_uploads: bool = True,
    ):
        self.factory = factory
        self.dispatcher = dispatcher
        self.settings = settings
        self.maintenance = maintenance
        # The service holds the uploads' part files (<data_dir>/uploads); a worker on another
        # machine or container must not delete rows whose files it cannot see.
        self.expire_uploads = expire_uploads
        self.interval_s = float(settings.job_sweep_interval_s)
        self.maintenance_interval_s = float(settings.maintenance_interval_s)
        self._next_maintenance = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def run_once(self) -> SweepResult | None:
        try:
            with self.factory() as session:
                return sweep(
                    session,
                    self.dispatcher,
                    queued_stale_after_s=float(self.settings.job_queued_stale_after_s),
                    running_stale_after_s=float(self.settings.job_stale_after_s),
                    backoff_max_s=float(self.settings.job_dispatch_backoff_max_s),
                )
        except Exception:  # a database hiccup must not kill the sweeper thread
            log.exception("sweeper: sweep failed")
            return None

    def maintain_once(self) -> MaintenanceResult | None:
        try:
            with self.factory() as session:
                return maintain(
                    session,
                    uploads_dir=uploads_dir(self.settings) if self.expire_uploads else None,
                    upload_older_than=timedelta(seconds=self.settings.upload_expire_after_s),
                    work_root=jobs.work_root(),
                    # No attempt outlives the hard time limit: an unowned folder older than
                    # that (plus a margin) belongs to nobody.
                    unowned_folder_older_than_s=float(self.settings.job_time_limit_s) + 600,
                )
        except Exception:
            log.exception("sweeper: maintenance failed")
            return None

    def _tick(self) -> None:
        self.run_once()
        if self.maintenance and time.monotonic() >= self._next_maintenance:
            self._next_maintenance = time.monotonic() + self.maintenance_interval_s
            self.maintain_once()

    def _loop(self) -> None:
        self._tick()
        while not self._stop.wait(self.interval_s):
            self._tick()

    def start(self) -> Sweeper:
        self._thread = threading.Thread(target=self._loop, name="job-sweeper", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
