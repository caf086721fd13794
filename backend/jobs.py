"""The reconstruction job's state machine, and how a job is handed to the workers.

States: ``queued → running → succeeded | failed``; ``failed → queued`` by :func:`retry`.
Every function here is keyword-only, takes a session, does one transition and COMMITS it
(one transaction each), so the Celery worker (``worker.tasks``) can call them directly.
Transitions that do not apply raise :class:`JobStateError` (the API answers 409).

:func:`mark_succeeded` stores the model directory under a fresh storage prefix and creates
the model row in the same transaction: if the commit fails the stored files are deleted
again, so a model version is either complete (files + row) or absent. It is idempotent: a
task delivered twice (``acks_late``) gets the model it already made.

:func:`enqueue` sends the task *by name* through a dispatcher, so the library service never
imports the numerical code. ``CeleryDispatcher`` is the real one (configured from settings);
tests inject anything with the same ``send_task`` method.
"""

from __future__ import annotations

import json
import logging
import math
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from backend import crud
from backend.storage import Storage, StorageError
from backend.tables import Job, JobKind, JobState, Model, Scan

log = logging.getLogger("backend.jobs")

RECONSTRUCT_TASK = "worker.tasks.reconstruct_scan"
# Task name per job kind (worker.tasks); the library sends by name, never imports the worker.
TASK_BY_KIND = {
    JobKind.reconstruct: RECONSTRUCT_TASK,
    JobKind.derive: "worker.tasks.derive_assets",
    JobKind.register: "worker.tasks.register_tablet",
}
_DONE = (JobState.succeeded, JobState.failed)


class JobStateError(ValueError):
    """The job is not in a state that allows this transition."""

    def __init__(self, job: Job, action: str):
        super().__init__(f"job {job.id} is {job.state.value}: cannot {action}")
        self.job_id = job.id
        self.state = job.state


class Dispatcher(Protocol):
    def send_task(self, name: str, *, args: list[Any], task_id: str) -> Any: ...


class CeleryDispatcher:
    """Sends tasks by name to the broker of ``broker_url`` on ``queue``; no worker import."""

    def __init__(self, *, broker_url: str, queue: str):
        self.broker_url = broker_url
        self.queue = queue
        self._app = None

    def send_task(self, name: str, *, args: list[Any], task_id: str) -> Any:
        if self._app is None:
            from celery import Celery

            self._app = Celery("hammurabi-backend", broker=self.broker_url)
        # A short publish retry: a dead broker must fail the request, not hang it.
        return self._app.send_task(
            name,
            args=args,
            task_id=task_id,
            queue=self.queue,
            retry=True,
            retry_policy={"max_retries": 2, "interval_start": 0, "interval_step": 0.5},
        )


class RecordingDispatcher:
    """Keeps what would have been sent (tests, and deployments without workers)."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, list[Any], str]] = []

    def send_task(self, name: str, *, args: list[Any], task_id: str) -> None:
        self.sent.append((name, list(args), task_id))


def dispatcher_from_settings(settings: Any) -> CeleryDispatcher:
    from backend.queue import broker_url

    return CeleryDispatcher(broker_url=broker_url(settings), queue=settings.job_queue)


def _now() -> datetime:
    return datetime.now(UTC)


def _load(session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id, with_for_update=True, populate_existing=True)
    if job is None:
        raise LookupError(f"job_id: no job {job_id}")
    return job


def create(
    session: Session,
    *,
    scan: Scan | None = None,
    tablet_id: int | None = None,
    kind: JobKind = JobKind.reconstruct,
) -> Job:
    """A queued job for ``scan``, or for a whole tablet (``tablet_id``, e.g. registration).

    Flushed, not committed: it joins the caller's transaction (the new scan's).
    """
    if (scan is None) == (tablet_id is None):
        raise ValueError("give exactly one of scan and tablet_id")
    job = Job(
        scan_id=scan.id if scan is not None else None,
        tablet_id=scan.tablet_id if scan is not None else tablet_id,
        kind=kind,
        state=JobState.queued,
    )
    session.add(job)
    session.flush()
    return job


def enqueue(job: Job, *, dispatcher: Dispatcher) -> str:
    """Send the job to the workers by task name; return the task id.

    Call only after the job row is committed (a fast worker must find it).
    """
    task_id = f"job-{job.id}-attempt-{job.attempts + 1}"
    dispatcher.send_task(TASK_BY_KIND[job.kind], args=[job.id], task_id=task_id)
    return task_id


def mark_running(session: Session, *, job_id: int) -> Job:
    """queued → running (or running again after a lost worker: the task is redelivered)."""
    job = _load(session, job_id)
    if job.state in _DONE:
        raise JobStateError(job, "start it")
    job.state = JobState.running
    job.attempts += 1
    job.started_at = job.heartbeat_at = _now()
    job.progress = 0.0
    job.stage = None
    job.error = None
    session.commit()
    return job


def report_progress(
    session: Session,
    *,
    job_id: int,
    stage: str,
    fraction: float,
    timings_s: dict[str, float] | None = None,
) -> Job:
    """Record progress of a running job: ``fraction`` in [0, 1]; per-stage ``timings_s``."""
    if not (isinstance(fraction, int | float) and math.isfinite(fraction) and 0 <= fraction <= 1):
        raise ValueError(f"fraction must be a number in [0, 1], got {fraction!r}")
    if not stage or len(stage) > 100:
        raise ValueError(f"stage must be a name of 1-100 characters, got {stage!r}")
    job = _load(session, job_id)
    if job.state != JobState.running:
        raise JobStateError(job, "report progress")
    job.stage = stage
    job.progress = float(fraction)
    job.heartbeat_at = _now()
    if timings_s:
        job.timings = {**(job.timings or {}), **_check_timings(timings_s)}
    session.commit()
    return job


def _check_timings(timings_s: dict[str, float]) -> dict[str, float]:
    out = {}
    for name, seconds in timings_s.items():
        if not (isinstance(seconds, int | float) and math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"timings_s[{name!r}] must be seconds >= 0, got {seconds!r}")
        out[str(name)] = float(seconds)
    return out


def mark_failed(session: Session, *, job_id: int, error: str) -> Job:
    """queued/running → failed with a message for people (no traceback)."""
    if not error:
        raise ValueError("error must be a non-empty message")
    job = _load(session, job_id)
    if job.state in _DONE:
        raise JobStateError(job, "fail it")
    job.state = JobState.failed
    job.error = error[:4000]
    job.finished_at = _now()
    session.commit()
    return job


def retry(session: Session, *, job_id: int) -> Job:
    """failed → queued, clearing progress and error; the caller then calls :func:`enqueue`."""
    job = _load(session, job_id)
    if job.state != JobState.failed:
        raise JobStateError(job, "retry it (only failed jobs can be retried)")
    job.state = JobState.queued
    job.progress = 0.0
    job.stage = None
    job.error = None
    job.timings = {}
    job.started_at = job.finished_at = None
    job.enqueued_at = _now()
    session.commit()
    return job


def mark_enqueued(session: Session, *, job_id: int) -> Job:
    job = _load(session, job_id)
    job.enqueued_at = _now()
    session.commit()
    return job


def next_version(session: Session, *, tablet_id: int, face: str | None) -> int:
    """1 + the highest model version of this tablet's ``face`` (a re-scan adds a version).

    ``face=None`` counts the whole-tablet models (made from several scans, ``scan_id`` NULL).
    """
    query = select(func.max(Model.version)).where(Model.tablet_id == tablet_id)
    if face is None:
        query = query.where(Model.scan_id.is_(None))
    else:
        query = query.join(Scan, Model.scan_id == Scan.id).where(Scan.face == face)
    return (session.scalar(query) or 0) + 1


def mark_succeeded(
    session: Session,
    *,
    job_id: int,
    model_dir: Path,
    storage: Storage,
    report: dict[str, Any] | None = None,
) -> Model:
    """running → succeeded: store ``model_dir`` and create its model row, in one transaction.

    ``report`` defaults to ``model_dir/report.json``. Returns the model (the existing one if
    the job already succeeded).
    """
    model_dir = Path(model_dir)
    job = _load(session, job_id)
    if job.state == JobState.succeeded and job.model_id is not None:
        model = session.get(Model, job.model_id)
        if model is not None:
            return model
    if job.state != JobState.running:
        raise JobStateError(job, "mark it succeeded")
    if not (model_dir / "model.glb").is_file():
        raise ValueError(f"model_dir {str(model_dir)!r} holds no model.glb")
    if report is None:
        report = _read_report(model_dir)
    scan = session.get(Scan, job.scan_id) if job.scan_id is not None else None
    if job.scan_id is not None and scan is None:
        raise LookupError(f"job {job.id}: its scan is gone")
    face = scan.face if scan is not None else None
    version = next_version(session, tablet_id=job.tablet_id, face=face)
    # Readable and unique (the uuid): two racing jobs of one face never share a prefix, and
    # nothing ever overwrites a stored version.
    prefix = f"models/{job.tablet_id}/{face or 'tablet'}/v{version}-{uuid.uuid4().hex[:12]}"
    stats = storage.put_tree(prefix, model_dir)
    try:
        assets = {
            s.key[len(prefix) + 1 :]: {"size_bytes": s.size_bytes, "sha256": s.etag} for s in stats
        }
        model = Model(
            scan_id=job.scan_id,
            tablet_id=job.tablet_id,
            job_id=job.id,
            version=version,
            storage_prefix=prefix,
            report=report,
            assets=assets,
        )
        session.add(model)
        session.flush()
        job.model_id = model.id
        job.state = JobState.succeeded
        job.progress = 1.0
        job.finished_at = _now()
        crud.refresh_has_3d(session, tablet_id=job.tablet_id)
        session.commit()
    except BaseException:
        session.rollback()
        try:
            storage.delete_prefix(prefix)
        except StorageError:
            log.exception("could not remove %s after a failed commit", prefix)
        raise
    return model


def _read_report(model_dir: Path) -> dict[str, Any]:
    path = model_dir / "report.json"
    if not path.is_file():
        return {}
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"model_dir report.json cannot be read: {exc}") from exc
    return report if isinstance(report, dict) else {"report": report}
