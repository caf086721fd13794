"""Every state change of a job, in one place: create, claim, heartbeat, progress, retry,
dispatch bookkeeping, derived assets, success, failure.

States: ``queued → running → succeeded | failed``; ``failed → queued`` by :func:`retry`;
``running → queued`` when the attempt's worker is gone (:func:`requeue_stale`) or waits for
a transient error (:func:`wait_to_retry`). A queued job whose message could not be sent is
*awaiting dispatch* (``enqueued_at`` NULL, ``dispatch_after`` set, stage
:data:`AWAITING_DISPATCH`): ``backend.dispatch`` sends it again with backoff, it is never
failed because of a broker outage.

Every function here is keyword-only, takes a session, does one transition and COMMITS it
(one transaction each), so the Celery worker (``worker.tasks``) calls them directly and
never edits job rows itself. Transitions that do not apply raise :class:`JobStateError`
(the API answers 409), except the compare-and-set ones (claim, heartbeat, requeue) that
answer whether they won.

Attempts and owners: a worker *claims* a job with one conditional UPDATE that bumps
``attempts`` and records ``claimed_by`` (host, pid namespace, pid, process start time:
:func:`process_owner`). The attempt number is the token of that attempt: heartbeats and
hand-backs only act while it is current, so a job never runs twice at once. A redelivered
message may take over a running job at once when its owner is provably dead
(:func:`owner_is_dead`: same host and pid namespace, process gone), else only once its
heartbeat is stale.

:func:`mark_succeeded` stores the model directory under a fresh storage prefix and creates
the model row in the same transaction: if the commit fails the stored files are deleted
again, so a model version is either complete (files + row) or absent. It is idempotent: a
task delivered twice (``acks_late``) gets the model it already made.

Work folders (:func:`make_work_folder`) carry their owner, so a worker starting up or the
sweeper removes exactly the folders of dead attempts (:func:`remove_dead_work_folders`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import socket
import tempfile
import time
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import exists, func, select, update
from sqlalchemy.orm import Session

from backend import crud

# Re-exported: the transports live with the broker (backend.queue); callers import them here.
from backend.queue import CeleryDispatcher, Dispatcher, RecordingDispatcher  # noqa: F401
from backend.storage import Storage, StorageError
from backend.tables import Job, JobKind, JobState, Model, Scan, Tablet

log = logging.getLogger("backend.jobs")

RECONSTRUCT_TASK = "worker.tasks.reconstruct_scan"
# Task name per job kind (worker.tasks); the library sends by name, never imports the worker.
TASK_BY_KIND = {
    JobKind.reconstruct: RECONSTRUCT_TASK,
    JobKind.derive: "worker.tasks.derive_assets",
    JobKind.register: "worker.tasks.register_tablet",
}
AWAITING_DISPATCH = "awaiting dispatch"
WAITING_TO_RETRY = "waiting to retry"
WORK_FOLDER_PREFIXES = ("hammurabi-job-", "hammurabi-derive-", "hammurabi-register-")
OWNER_FILE = ".owner"
_DONE = (JobState.succeeded, JobState.failed)


class JobStateError(ValueError):
    """The job is not in a state that allows this transition."""

    def __init__(self, job: Job, action: str):
        super().__init__(f"job {job.id} is {job.state.value}: cannot {action}")
        self.job_id = job.id
        self.state = job.state


def now_utc() -> datetime:
    return datetime.now(UTC)


def _load(session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id, with_for_update=True, populate_existing=True)
    if job is None:
        raise LookupError(f"job_id: no job {job_id}")
    return job


def _beat():
    return func.coalesce(Job.heartbeat_at, Job.started_at, Job.created_at)


# -- owners: which process runs an attempt, and is it still alive? ------------------------


def _proc_stat(pid: int) -> tuple[str, str] | None:
    """(state letter, start time in clock ticks since boot) of ``pid`` from /proc, or None."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[-1].split()  # the command name may hold spaces
    return fields[0], fields[19]


def _pid_namespace() -> str:
    try:
        return os.readlink("/proc/self/ns/pid").removeprefix("pid:").strip("[]")
    except OSError:
        return "-"


def process_owner(pid: int | None = None) -> str:
    """``host/pidns/pid/start`` of this process: unique among the processes ever alive on a
    host (the start time tells a reused pid from the original)."""
    pid = os.getpid() if pid is None else pid
    stat = _proc_stat(pid)
    return f"{socket.gethostname()}/{_pid_namespace()}/{pid}/{stat[1] if stat else '-'}"


def owner_is_dead(owner: str | None) -> bool:
    """True only when ``owner`` (:func:`process_owner`) is provably gone: it ran on this host
    in this pid namespace and its process no longer exists (or is a zombie, or the pid now
    belongs to a later process). Owners elsewhere are judged by heartbeat, not here."""
    if not owner:
        return False
    parts = owner.split("/")
    if len(parts) != 4 or parts[0] != socket.gethostname() or parts[1] != _pid_namespace():
        return False
    try:
        pid = int(parts[2])
    except ValueError:
        return False
    stat = _proc_stat(pid)
    if stat is None:
        if Path("/proc/self/stat").exists():
            return True
        try:  # no /proc: ask the kernel
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            return False
        return False
    state, start = stat
    return state in ("Z", "X") or (parts[3] != "-" and start != parts[3])


# -- creation and dispatch bookkeeping (backend.dispatch does the sending) ----------------


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


def _registration_due(session: Session, tablet_id: int) -> bool:
    """Models of >= 2 faces, no register job queued/running, no reconstruction of the tablet
    queued/running, and a face model it has not seen.

    A registration reads the models when it starts, so it covers the face models created
    before its latest ``started_at`` (or ``created_at`` if it never started). Waiting for the
    tablet's pending reconstructions registers a set of faces uploaded together once, when
    its last face is in, instead of once per face (each registration of six faces at 26.8 µm
    costs minutes); the last reconstruction to finish triggers it.
    """
    face_models = (
        select(Model.id).join(Scan, Model.scan_id == Scan.id).where(Model.tablet_id == tablet_id)
    )
    faces = session.scalar(
        select(func.count(func.distinct(Scan.face)))
        .select_from(Model)
        .join(Scan, Model.scan_id == Scan.id)
        .where(Model.tablet_id == tablet_id)
    )
    if faces < 2:
        return False
    pending = [JobState.queued, JobState.running]
    register = select(Job).where(Job.tablet_id == tablet_id, Job.kind == JobKind.register)
    if session.scalar(select(exists(register.where(Job.state.in_(pending))))):
        return False
    reconstructing = select(Job).where(
        Job.tablet_id == tablet_id, Job.kind == JobKind.reconstruct, Job.state.in_(pending)
    )
    if session.scalar(select(exists(reconstructing))):
        return False
    last = session.scalar(register.order_by(Job.id.desc()).limit(1))
    if last is None:
        return True
    seen_until = last.started_at or last.created_at
    return bool(session.scalar(select(exists(face_models.where(Model.created_at > seen_until)))))


def create_registration_if_due(session: Session, *, tablet_id: int) -> Job | None:
    """A new queued register job for the tablet if one is due (committed), else None.

    Due: models of two or more faces, no register job queued or running, no reconstruction
    of the tablet queued or running (a set of faces is registered once, after its last
    face), and a face model newer than the start of the last registration. The tablet row is locked (PostgreSQL) so
    two faces finishing at once make one job; on SQLite the second writer waits or fails
    with OperationalError (transient).
    """
    if session.get(Tablet, tablet_id, with_for_update=True) is None:
        session.rollback()
        return None
    if not _registration_due(session, tablet_id):
        session.rollback()
        return None
    job = create(session, tablet_id=tablet_id, kind=JobKind.register)
    session.commit()
    return job


def task_id(job: Job) -> str:
    """The Celery task id of the next message for ``job`` (re-sends repeat it: no result
    backend keys on it, and the worker's claim, not the id, tells duplicates apart)."""
    return f"job-{job.id}-attempt-{job.attempts + 1}"


def mark_dispatched(session: Session, *, job_id: int) -> Job:
    """The job's message is with the broker: clear any pending dispatch.

    Leaves the state alone: a fast worker may have claimed the job already.
    """
    job = _load(session, job_id)
    if job.state == JobState.queued:
        job.enqueued_at = now_utc()
        if job.stage == AWAITING_DISPATCH:
            job.stage = None
    job.dispatch_failures = 0
    job.dispatch_after = None
    session.commit()
    return job


def mark_awaiting_dispatch(session: Session, *, job_id: int, retry_in_s: float) -> Job:
    """The broker could not take the job: it stays queued, to be sent after ``retry_in_s``.

    A job that a worker took meanwhile (a message did get through) is left alone.
    """
    if not (math.isfinite(retry_in_s) and retry_in_s >= 0):
        raise ValueError(f"retry_in_s must be seconds >= 0, got {retry_in_s!r}")
    job = _load(session, job_id)
    if job.state == JobState.queued:
        job.enqueued_at = None
        job.stage = AWAITING_DISPATCH
        job.dispatch_failures = (job.dispatch_failures or 0) + 1
        job.dispatch_after = now_utc() + timedelta(seconds=retry_in_s)
    session.commit()
    return job


def take_due_dispatch(session: Session, *, job_id: int, now: datetime, hold_s: float) -> bool:
    """Compare-and-set: this process will send the awaiting job ``job_id`` (due by ``now``);
    others skip it for ``hold_s``. False when another sender or a worker got there first."""
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.queued, Job.dispatch_after <= now)
        .values(dispatch_after=now + timedelta(seconds=hold_s))
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


# -- claims, heartbeats, hand-backs --------------------------------------------------------


def claim(
    session: Session, *, job_id: int, running_stale_after_s: float, owner: str | None = None
) -> int | None:
    """Start ``job_id`` for ``owner`` (default: this process); its attempt number, or None.

    Takes a queued job, or a running one whose attempt is dead: heartbeat older than
    ``running_stale_after_s``, or its owner provably gone (:func:`owner_is_dead`, e.g. a
    redelivery after a kill -9 on this host). The take-over is ONE conditional UPDATE on the
    attempt seen (compare-and-set, atomic on SQLite and PostgreSQL): two claimers never both
    win. A finished job, or one running with a live owner, is left alone (None).
    """
    owner = owner or process_owner()
    now = now_utc()
    row = session.execute(
        select(Job.state, Job.attempts, Job.claimed_by, _beat()).where(Job.id == job_id)
    ).first()
    session.rollback()  # end the read before the write (SQLite)
    if row is None or row[0] in _DONE:
        return None
    state, attempts, claimed_by, beat = row
    condition = Job.state == JobState.queued
    if state == JobState.running:
        cutoff = now - timedelta(seconds=running_stale_after_s)
        if _aware(beat) < cutoff:
            condition = (Job.state == JobState.running) & (_beat() < cutoff)
        elif owner_is_dead(claimed_by):
            condition = (Job.state == JobState.running) & (Job.claimed_by == claimed_by)
        else:
            return None
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, condition, Job.attempts == attempts)
        .values(
            state=JobState.running,
            attempts=attempts + 1,
            claimed_by=owner,
            started_at=now,
            heartbeat_at=now,
            progress=0.0,
            stage="starting",
            error=None,
            dispatch_after=None,
        )
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return attempts + 1 if result.rowcount == 1 else None


def _aware(moment: datetime | None) -> datetime:
    if moment is None:
        return datetime.min.replace(tzinfo=UTC)
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def heartbeat(session: Session, *, job_id: int, attempt: int) -> bool:
    """Refresh the heartbeat of ``job_id`` if it is still running as ``attempt``.

    Returns False when the job is no longer ours (finished, or taken over after we were
    thought dead): the caller should stop working on it.
    """
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.running, Job.attempts == attempt)
        .values(heartbeat_at=now_utc())
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


def wait_to_retry(session: Session, *, job_id: int, attempt: int) -> bool:
    """running → queued while ``attempt`` waits out a transient error (Celery retries it).

    False if the attempt is no longer current (nothing changed)."""
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.running, Job.attempts == attempt)
        .values(state=JobState.queued, stage=WAITING_TO_RETRY, enqueued_at=now_utc())
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


def requeue_lost(session: Session, *, job_id: int, cutoff: datetime, now: datetime) -> bool:
    """A queued job sent before ``cutoff`` and never picked up: claim it for re-sending (its
    ``enqueued_at`` moves to ``now``, so other sweepers skip it for a period)."""
    since = func.coalesce(Job.enqueued_at, Job.created_at)
    result = session.execute(
        update(Job)
        .where(
            Job.id == job_id,
            Job.state == JobState.queued,
            Job.dispatch_after.is_(None),
            since < cutoff,
        )
        .values(enqueued_at=now, stage=None)
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


def requeue_stale(
    session: Session, *, job_id: int, attempt: int, cutoff: datetime | None, now: datetime
) -> bool:
    """running → queued for a dead ``attempt``: its heartbeat is older than ``cutoff``, or
    (``cutoff`` None) its owner was found dead by the caller. Compare-and-set on the attempt."""
    condition = Job.attempts == attempt
    if cutoff is not None:
        condition = condition & (_beat() < cutoff)
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.running, condition)
        .values(state=JobState.queued, enqueued_at=now, stage=None)
        .execution_options(synchronize_session=False)
    )
    session.commit()
    return result.rowcount == 1


def mark_running(session: Session, *, job_id: int) -> Job:
    """queued → running unconditionally (tests and benches; workers use :func:`claim`)."""
    job = _load(session, job_id)
    if job.state in _DONE:
        raise JobStateError(job, "start it")
    job.state = JobState.running
    job.attempts += 1
    job.claimed_by = process_owner()
    job.started_at = job.heartbeat_at = now_utc()
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
    job.heartbeat_at = now_utc()
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
    job.finished_at = now_utc()
    session.commit()
    return job


def retry(session: Session, *, job_id: int) -> Job:
    """failed → queued, clearing progress and error; the caller then dispatches it
    (``backend.dispatch.dispatch``)."""
    job = _load(session, job_id)
    if job.state != JobState.failed:
        raise JobStateError(job, "retry it (only failed jobs can be retried)")
    job.state = JobState.queued
    job.progress = 0.0
    job.stage = None
    job.error = None
    job.timings = {}
    job.started_at = job.finished_at = None
    job.enqueued_at = None
    session.commit()
    return job


def finish_without_model(session: Session, *, job_id: int) -> Job:
    """running → succeeded for a job that makes no model (the queue's no-op benchmark)."""
    job = _load(session, job_id)
    if job.state != JobState.running:
        raise JobStateError(job, "mark it succeeded")
    job.state = JobState.succeeded
    job.progress = 1.0
    job.finished_at = now_utc()
    session.commit()
    return job


def store_derived_assets(
    session: Session, *, job_id: int, model_id: int, assets: dict[str, dict[str, Any]]
) -> Job:
    """running → succeeded for a derive job: merge ``assets`` (name → size_bytes, sha256)
    into model ``model_id``'s asset list in the same transaction."""
    job = _load(session, job_id)
    if job.state != JobState.running:
        raise JobStateError(job, "store derived assets")
    model = session.get(Model, model_id, with_for_update=True)
    if model is None:
        raise LookupError(f"model_id: no model {model_id}")
    model.assets = {**(model.assets or {}), **assets}
    job.state = JobState.succeeded
    job.progress = 1.0
    job.model_id = model_id
    job.finished_at = now_utc()
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


# The tiles of a model (worker/tiles; thousands of files) are recorded once: the model's
# assets list tiles/index.json and tiles/files.json (every tile's size and SHA-256); the
# asset route finds the other names under tiles/ in files.json.
TILES_PREFIX = "tiles/"
TILES_RECORDED = ("index.json", "files.json")


def recorded_assets(assets: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The asset entries kept in the model row: all but the files inside a tiles/ folder
    (``tiles/`` or ``faces/<label>/tiles/``), whose index and file list only are kept."""
    return {
        name: info
        for name, info in assets.items()
        if tiles_part(name) is None or tiles_part(name) in TILES_RECORDED
    }


def tiles_part(name: str) -> str | None:
    """The name inside its tiles/ folder, or None when it is not in one."""
    head, sep, rest = name.partition(TILES_PREFIX)
    if not sep or (head and not head.endswith("/")):
        return None
    return rest


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
        assets = recorded_assets(
            {
                s.key[len(prefix) + 1 :]: {"size_bytes": s.size_bytes, "sha256": s.etag}
                for s in stats
            }
        )
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
        job.finished_at = now_utc()
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


# -- work folders --------------------------------------------------------------------------


def work_root() -> Path:
    """Where the workers make their work folders (``$TMPDIR`` or the system's temp dir)."""
    return Path(tempfile.gettempdir())


def make_work_folder(root: Path, *, job_id: int, attempt: int, kind: str = "job") -> Path:
    """A fresh folder under ``root`` for one attempt, marked with its owner process."""
    prefix = f"hammurabi-{kind}-{job_id}-a{attempt}-"
    if not any(prefix.startswith(p) for p in WORK_FOLDER_PREFIXES):
        raise ValueError(f"kind must be one of job, derive, register; got {kind!r}")
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=root))
    (folder / OWNER_FILE).write_text(process_owner())
    return folder


def remove_dead_work_folders(root: Path, *, unowned_older_than_s: float) -> list[Path]:
    """Remove the work folders under ``root`` whose attempt is dead; return them.

    Dead: the owner in the folder's ``.owner`` is provably gone (:func:`owner_is_dead`), or
    the folder has no owner (older code, or a crash before it was written) and was last
    changed more than ``unowned_older_than_s`` ago (no attempt outlives the time limit).
    Folders of live attempts, and of other hosts, are left alone.
    """
    removed = []
    cutoff = time.time() - unowned_older_than_s
    for prefix in WORK_FOLDER_PREFIXES:
        for folder in Path(root).glob(f"{prefix}*"):
            try:
                if not folder.is_dir() or folder.is_symlink():
                    continue
                owner_file = folder / OWNER_FILE
                if owner_file.is_file():
                    dead = owner_is_dead(owner_file.read_text().strip())
                else:
                    dead = folder.stat().st_mtime < cutoff
            except OSError:
                continue
            if dead:
                shutil.rmtree(folder, ignore_errors=True)
                removed.append(folder)
    if removed:
        log.warning("removed %d work folders of dead attempts under %s", len(removed), root)
    return removed
