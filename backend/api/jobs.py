"""Reconstruction jobs: ``GET /jobs/{id}`` and ``POST /jobs/{id}/retry`` (staff/admin).

Also the dispatcher dependency: ``app.state.dispatcher`` (tests set a recording one), made
from settings (Celery, by task name) on first use.
"""

from __future__ import annotations

import logging
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request
from pydantic import BaseModel
from sqlalchemy.orm import Session

from backend import jobs
from backend.api.deps import OptionalUser, SessionDep
from backend.api.models import StorageErrorRoute, check_tablet_access
from backend.errors import ApiError, not_found
from backend.tables import Job, JobState

log = logging.getLogger("backend.api.jobs")


def get_dispatcher(request: Request) -> jobs.Dispatcher:
    dispatcher = getattr(request.app.state, "dispatcher", None)
    if dispatcher is None:
        dispatcher = jobs.dispatcher_from_settings(request.app.state.settings)
        request.app.state.dispatcher = dispatcher
    return dispatcher


DispatcherDep = Annotated[Any, Depends(get_dispatcher)]


class JobOut(BaseModel):
    id: int
    scan_id: int | None
    tablet_id: int
    kind: str
    state: str
    progress: float
    stage: str | None
    timings: dict[str, Any]
    error: str | None
    attempts: int
    model_id: int | None
    created_at: datetime
    enqueued_at: datetime | None
    started_at: datetime | None
    finished_at: datetime | None

    @classmethod
    def of(cls, job: Job) -> JobOut:
        return cls(
            id=job.id,
            scan_id=job.scan_id,
            tablet_id=job.tablet_id,
            kind=job.kind.value,
            state=job.state.value,
            progress=job.progress,
            stage=job.stage,
            timings=job.timings or {},
            error=job.error,
            attempts=job.attempts,
            model_id=job.model_id,
            created_at=job.created_at,
            enqueued_at=job.enqueued_at,
            started_at=job.started_at,
            finished_at=job.finished_at,
        )


def send(session: Session, job: Job, dispatcher: Any) -> Job:
    """Enqueue a committed job; a broker that cannot take it fails the job (retry later)."""
    try:
        jobs.enqueue(job, dispatcher=dispatcher)
    except Exception as exc:  # any broker/transport failure: kept visible on the job
        log.exception("could not enqueue job %s", job.id)
        return jobs.mark_failed(
            session, job_id=job.id, error=f"could not reach the job queue: {type(exc).__name__}"
        )
    return jobs.mark_enqueued(session, job_id=job.id)


router = APIRouter(prefix="/jobs", tags=["jobs"], route_class=StorageErrorRoute)


def _job(session: Session, user, job_id: int, *, edit: bool) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise not_found(f"job {job_id}", where="job_id")
    check_tablet_access(
        session, user, job.tablet_id, what=f"job {job_id}", where="job_id", edit=edit
    )
    return job


@router.get("/{job_id}", response_model=JobOut)
def read_job(job_id: Annotated[int, Path(ge=1)], session: SessionDep, user: OptionalUser):
    return JobOut.of(_job(session, user, job_id, edit=False))


@router.post("/{job_id}/retry", response_model=JobOut)
def retry_job(
    job_id: Annotated[int, Path(ge=1)],
    session: SessionDep,
    user: OptionalUser,
    dispatcher: DispatcherDep,
):
    """Queue a failed job again (staff of the tablet's institution, admins); else 409."""
    job = _job(session, user, job_id, edit=True)
    if job.state != JobState.failed:
        raise ApiError(409, f"job {job_id} is {job.state.value}: only failed jobs can be retried")
    job = jobs.retry(session, job_id=job.id)
    return JobOut.of(send(session, job, dispatcher))
