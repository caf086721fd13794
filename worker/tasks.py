"""Thin Celery tasks: job ids in, the job row out (state, progress, timings, model).

- ``worker.tasks.reconstruct_scan(job_id)``: fetch the scan's bundle from storage,
  ``worker.pipeline.reconstruct_bundle``, derive the viewer's assets (``worker.assets``), build
  the tiles for streaming (``worker.tiles``), store the model directory and its row (``backend.jobs.mark_succeeded``: files + row together).
- ``worker.tasks.derive_assets(job_id)``: (re)derive the assets and the tiles of the latest
  model of the job's scan, e.g. for models made before an asset existed.
- ``worker.tasks.register_tablet(job_id)``: register a tablet's faces with
  ``worker.register`` when that module exists (another engineer's).

Registration starts by itself: after a reconstruction succeeds (and after a registration
ends) :func:`schedule_registration` creates and sends ONE register job for the tablet when
it has models of two or more faces, none is queued or running, no reconstruction of the
tablet is queued or running (a set of faces uploaded together is registered once, when its
last face is in), and a face model is newer than the start of the last registration. Redelivered messages find that job and add none.

Thin: every change of a job row is a call into ``backend.jobs`` (claim, heartbeat, progress,
retry wait, derived assets, success, failure) and every send goes through
``backend.dispatch``; this module never edits a job row itself.

Idempotent: the job row is claimed with one compare-and-set UPDATE (``backend.jobs.claim``)
before any work, so a redelivered or duplicated message finishes the same job or does
nothing; a redelivery after a kill takes the job over at once when the dead attempt's
process is provably gone; ``models.job_id`` is unique, so one job never makes two model
versions. A thread refreshes the heartbeat every ``job_heartbeat_interval_s``; the sweeper
re-sends jobs whose worker died. Work folders carry their owner, so the folders of killed
attempts are removed when a worker starts and by the sweeper.

Retries: only the transient errors named in :data:`TRANSIENT` (storage unavailable, database
connection lost, network), with exponential backoff; anything else fails the job with a
message for people.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError, OperationalError

from backend import dispatch, jobs, queue
from backend.storage import StorageError, storage_from_settings
from backend.tables import Job, JobKind, JobState, Model, Scan
from worker import celery_app as capp
from worker.assets import AssetError
from worker.assets import derive_assets as write_derived_assets
from worker.celery_app import app
from worker.photos import write_photo_assets
from worker.tiles import TileError, build_tiles
from worker.trust_assets import QUALITY_INPUTS

log = logging.getLogger("worker.tasks")

MAX_RETRIES = 5
PROGRESS_MIN_INTERVAL_S = 0.5
# Set to a file path: while that file exists a running job waits at each progress report
# after "starting" (its work folder exists by then; heartbeat still beating). For
# maintenance and for the kill-mid-job tests.
PAUSE_FILE_ENV = "HAMMURABI_WORKER_PAUSE_FILE"


def is_transient(exc: BaseException) -> bool:
    """Errors worth retrying: the service will likely answer again in a while."""
    if isinstance(exc, StorageError):
        return exc.status_code == 503
    return isinstance(exc, OperationalError | ConnectionError | TimeoutError)


TRANSIENT = "storage 503, sqlalchemy OperationalError, ConnectionError, TimeoutError"


class JobLost(Exception):
    """The job was taken over by another worker (we were thought dead)."""


class _Beat:
    """Heartbeat thread + rate-limited progress reports for one claimed attempt."""

    def __init__(self, job_id: int, attempt: int):
        self.job_id = job_id
        self.attempt = attempt
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._last_report = 0.0
        self._last_stage: str | None = None
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{job_id}", daemon=True)

    def __enter__(self) -> _Beat:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5)

    def _run(self) -> None:
        period_s = float(capp.settings.job_heartbeat_interval_s)
        while not self._stop.wait(period_s):
            try:
                with capp.session_factory()() as session:
                    if not jobs.heartbeat(session, job_id=self.job_id, attempt=self.attempt):
                        self.lost.set()
                        return
            except Exception:  # the database may be briefly away; the sweeper is lenient
                log.warning("job %s: heartbeat failed", self.job_id, exc_info=True)

    def progress(self, stage: str, fraction: float, *, force: bool = False) -> None:
        now = time.monotonic()
        if (
            not force
            and stage == self._last_stage
            and now - self._last_report < PROGRESS_MIN_INTERVAL_S
        ):
            return
        self._last_report, self._last_stage = now, stage
        if self.lost.is_set():
            raise JobLost(f"job {self.job_id}: attempt {self.attempt} was taken over")
        try:
            with capp.session_factory()() as session:
                jobs.report_progress(
                    session,
                    job_id=self.job_id,
                    stage=stage,
                    fraction=min(1.0, max(0.0, fraction)),
                )
        except jobs.JobStateError:
            self.lost.set()
            raise JobLost(f"job {self.job_id} is no longer running") from None
        if stage != "starting":
            _wait_while_paused()

    def timings(self, timings_s: dict[str, float], stage: str, fraction: float) -> None:
        with capp.session_factory()() as session:
            jobs.report_progress(
                session, job_id=self.job_id, stage=stage, fraction=fraction, timings_s=timings_s
            )


def _wait_while_paused() -> None:
    pause = os.environ.get(PAUSE_FILE_ENV)
    while pause and os.path.exists(pause):
        time.sleep(0.1)


def _fail(job_id: int, message: str) -> None:
    # JobStateError: finished meanwhile (another attempt): nothing to record.
    with capp.session_factory()() as session, contextlib.suppress(jobs.JobStateError):
        jobs.mark_failed(session, job_id=job_id, error=message)


def _run_job(task, job_id: int, work: Callable[[_Beat, Job], str]) -> str:
    """Claim ``job_id``, run ``work`` with a heartbeat, and turn errors into job states."""
    with capp.session_factory()() as session:
        job = session.get(Job, job_id)
        if job is None:
            log.warning("job %s does not exist (deleted?): nothing to do", job_id)
            return "missing"
        if job.state in (JobState.succeeded, JobState.failed):
            return job.state.value  # a redelivered message after the job finished
        attempt = jobs.claim(
            session, job_id=job_id, running_stale_after_s=capp.settings.job_stale_after_s
        )
        if attempt is None:
            state = session.scalar(select(Job.state).where(Job.id == job_id))
            if state in (JobState.succeeded, JobState.failed):
                return state.value
            return "busy"  # running elsewhere with a live owner and heartbeat
        job = session.get(Job, job_id, populate_existing=True)
        session.expunge(job)
    try:
        with _Beat(job_id, attempt) as beat:
            beat.progress("starting", 0.0, force=True)
            return work(beat, job)
    except JobLost as exc:
        log.warning("%s", exc)
        return "lost"
    except SoftTimeLimitExceeded:
        _fail(job_id, f"took longer than the time limit ({capp.settings.job_time_limit_s:.0f} s)")
        return "failed"
    except Exception as exc:
        if is_transient(exc) and task.request.retries < MAX_RETRIES:
            countdown_s = min(300, 2 ** (task.request.retries + 2))
            log.warning("job %s: transient %r, retry in %s s", job_id, exc, countdown_s)
            with capp.session_factory()() as session:
                jobs.wait_to_retry(session, job_id=job_id, attempt=attempt)
            raise task.retry(exc=exc, countdown=countdown_s) from None
        log.exception("job %s failed", job_id)
        _fail(job_id, _message(exc))
        return "failed"


def _message(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    if isinstance(exc, ValueError | AssetError | StorageError | LookupError):
        return text
    return f"internal error ({type(exc).__name__}): {text}"


def _reconstruct(beat: _Beat, job: Job) -> str:
    from worker.pipeline import ReconstructionError, reconstruct_bundle

    storage = storage_from_settings(capp.settings)
    with capp.session_factory()() as session:
        scan = session.get(Scan, job.scan_id)
        if scan is None:
            raise LookupError(f"job {job.id}: its scan is gone")
        bundle_key = scan.bundle_key
    work = jobs.make_work_folder(jobs.work_root(), job_id=job.id, attempt=job.attempts, kind="job")
    try:
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        beat.progress("fetch", 0.01, force=True)
        bundle = storage.get_file(bundle_key, work / Path(bundle_key).name)
        timings["fetch"] = time.perf_counter() - t0

        def progress(stage: str, fraction: float) -> None:
            beat.progress(stage, 0.02 + 0.83 * fraction)  # reconstruction: 2 % … 85 %

        t0 = time.perf_counter()
        model_dir = work / "model"
        try:
            report = reconstruct_bundle(bundle, model_dir, progress=progress)
        except ReconstructionError as exc:
            _fail(job.id, f"reconstruction: {exc}")
            return "failed"
        timings["reconstruct"] = time.perf_counter() - t0
        timings.update({f"reconstruct.{k}": v for k, v in report.get("timings_s", {}).items()})

        t0 = time.perf_counter()
        beat.progress("assets", 0.86, force=True)
        write_derived_assets(model_dir)
        timings["assets"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        beat.progress("photos", 0.87, force=True)
        _photos(job.id, bundle, model_dir)
        timings["photos"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        beat.progress("tiles", 0.88, force=True)
        _build_tiles(model_dir, lambda stage, f: beat.progress("tiles", 0.88 + 0.04 * f))
        timings["tiles"] = time.perf_counter() - t0
        beat.timings(timings, "store", 0.92)

        if beat.lost.is_set():
            raise JobLost(f"job {job.id}: attempt {beat.attempt} was taken over")
        t0 = time.perf_counter()
        model = _store(job.id, model_dir, storage)
        log.info("job %s: model %s stored in %.1f s", job.id, model, time.perf_counter() - t0)
        return "succeeded"
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _photos(job_id: int, bundle: Path, model_dir: Path) -> None:
    """The photo stack and gloss (worker.photos): an addition to the model, so a failure
    there leaves the model without them (and says so in the log), never half of them."""
    try:
        write_photo_assets(bundle, model_dir)
    except Exception:
        log.exception("job %s: photo stack and gloss not written", job_id)
        shutil.rmtree(model_dir / "photos", ignore_errors=True)
        for name in ("gloss.png", "gloss.json"):
            (model_dir / name).unlink(missing_ok=True)


def _build_tiles(model_dir: Path, progress: Callable[[str, float], None]) -> None:
    """The model's tiles for streaming (worker.tiles). A model that cannot be tiled (a
    TileError names why) is still stored: the viewer falls back to model.glb."""
    try:
        build_tiles(model_dir, progress=progress)
    except TileError as exc:
        log.warning("%s: no tiles: %s", model_dir, exc)


def _store(job_id: int, model_dir: Path, storage) -> int:
    """mark_succeeded, tolerant of a concurrent attempt that stored first (unique job_id)."""
    with capp.session_factory()() as session:
        try:
            return jobs.mark_succeeded(
                session, job_id=job_id, model_dir=model_dir, storage=storage
            ).id
        except (IntegrityError, jobs.JobStateError):
            session.rollback()
            existing = session.scalar(select(Model.id).where(Model.job_id == job_id))
            if existing is None:
                raise
            return existing


def _derive(beat: _Beat, job: Job) -> str:
    storage = storage_from_settings(capp.settings)
    with capp.session_factory()() as session:
        model = session.scalar(
            select(Model).where(Model.scan_id == job.scan_id).order_by(Model.version.desc())
        )
        if model is None:
            raise LookupError(f"job {job.id}: scan {job.scan_id} has no model yet")
        prefix, model_id = model.storage_prefix, model.id
    work = jobs.make_work_folder(
        jobs.work_root(), job_id=job.id, attempt=job.attempts, kind="derive"
    )
    try:
        beat.progress("fetch", 0.1, force=True)
        quality = [f"quality/{n}.npy" for n in QUALITY_INPUTS]  # the trust map's inputs
        (work / "quality").mkdir(exist_ok=True)
        for name in (
            "height.npy",
            "normals.npy",
            "report.json",
            "albedo.png",
            "normals.png",
            "model.glb",
            *quality,
        ):
            key = f"{prefix}/{name}"
            if storage.exists(key):
                storage.get_file(key, work / name)
        beat.progress("assets", 0.3, force=True)
        names = write_derived_assets(work)
        # The tiles too (models made before worker.tiles existed get theirs here).
        beat.progress("tiles", 0.5, force=True)
        _build_tiles(work, lambda stage, f: beat.progress("tiles", 0.5 + 0.3 * f))
        beat.progress("store", 0.85, force=True)
        stats = {name: storage.put_file(f"{prefix}/{name}", work / name) for name in names}
        if (work / "tiles" / "index.json").is_file():
            for s in storage.put_tree(f"{prefix}/tiles", work / "tiles"):
                stats[s.key[len(prefix) + 1 :]] = s
        with capp.session_factory()() as session:
            jobs.store_derived_assets(
                session,
                job_id=job.id,
                model_id=model_id,
                assets=jobs.recorded_assets(
                    {n: {"size_bytes": s.size_bytes, "sha256": s.etag} for n, s in stats.items()}
                ),
            )
        return "succeeded"
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _register(beat: _Beat, job: Job) -> str:
    try:
        import worker.register as register  # noqa: F401  (another engineer's module)
    except ModuleNotFoundError as exc:
        if exc.name != "worker.register":
            raise
        _fail(job.id, "registration of faces is not available in this worker version")
        return "failed"
    run = getattr(register, "run_job", None)
    if run is None:
        _fail(job.id, "worker.register has no run_job(job_id, session_factory, storage, progress)")
        return "failed"
    return run(job.id, capp.session_factory(), storage_from_settings(capp.settings), beat.progress)


def dispatcher() -> queue.Dispatcher:
    """Where follow-up jobs go: the broker of the settings (tests replace this function)."""
    return queue.dispatcher_from_settings(capp.settings)


def schedule_registration(tablet_id: int) -> int | None:
    """Create (``backend.jobs.create_registration_if_due``) and send the tablet's register
    job if one is due; its id, or None. A send that fails leaves the job awaiting dispatch
    (``backend.dispatch``): the sweeper sends it later. On SQLite a concurrent writer fails
    with OperationalError, which the caller retries (transient)."""
    with capp.session_factory()() as session:
        job = jobs.create_registration_if_due(session, tablet_id=tablet_id)
        if job is None:
            return None
        dispatch.dispatch(
            session,
            job_id=job.id,
            dispatcher=dispatcher(),
            backoff_max_s=capp.settings.job_dispatch_backoff_max_s,
        )
        log.info("tablet %s: register job %s queued", tablet_id, job.id)
        return job.id


def _follow_up(task, job_id: int) -> None:
    """After a job ended: start the tablet's registration if due; never fails the job."""
    try:
        with capp.session_factory()() as session:
            tablet_id = session.scalar(select(Job.tablet_id).where(Job.id == job_id))
        if tablet_id is not None:
            schedule_registration(tablet_id)
    except Exception as exc:
        if is_transient(exc) and task.request.retries < MAX_RETRIES:
            # The redelivered task finds its job finished and only repeats this step.
            raise task.retry(exc=exc, countdown=min(300, 2 ** (task.request.retries + 2))) from None
        log.exception("job %s: could not schedule the tablet's registration", job_id)


_TASK_OPTIONS = {"bind": True, "acks_late": True, "max_retries": MAX_RETRIES}


@app.task(name=jobs.TASK_BY_KIND[JobKind.reconstruct], **_TASK_OPTIONS)
def reconstruct_scan(self, job_id: int) -> str:
    result = _run_job(self, int(job_id), _reconstruct)
    # Also on redelivery (a crash may have come before this step), and after a failure: the
    # registration waits for the tablet's pending reconstructions, so the last face of a set
    # starts it whether or not that face itself succeeded.
    if result in ("succeeded", "failed"):
        _follow_up(self, int(job_id))
    return result


@app.task(name=jobs.TASK_BY_KIND[JobKind.derive], **_TASK_OPTIONS)
def derive_assets(self, job_id: int) -> str:
    return _run_job(self, int(job_id), _derive)


@app.task(name=jobs.TASK_BY_KIND[JobKind.register], **_TASK_OPTIONS)
def register_tablet(self, job_id: int) -> str:
    result = _run_job(self, int(job_id), _register)
    if result in ("succeeded", "failed"):  # a face may have arrived while it ran
        _follow_up(self, int(job_id))
    return result


@app.task(name="worker.tasks.noop", bind=True, acks_late=True)
def noop(self, job_id: int) -> str:
    """Claims and finishes a job without work: measures the queue's overhead (bench/queue.py)."""
    return _run_job(self, int(job_id), lambda beat, job: _finish_noop(job.id))


def _finish_noop(job_id: int) -> str:
    with capp.session_factory()() as session:
        jobs.finish_without_model(session, job_id=job_id)
    return "succeeded"
