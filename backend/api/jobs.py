"""Reconstruction jobs: ``GET /jobs/{id}`` and ``POST /jobs/{id}/retry`` (staff/admin).

Also the dispatcher dependency: ``app.state.dispatcher`` (tests set a recording one), made
from settings (Celery, by task name) on first use. Sending is ``backend.dispatch``'s: a
broker outage leaves the job queued (awaiting dispatch), never failed.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request
from pydantic import BaseModel
from sqlalchemy.orm import Session

from backend import dispatch, jobs, queue
from backend.api.deps import OptionalUser, SessionDep
from backend.api.models import StorageErrorRoute, check_tablet_access
from backend.errors import ApiError, not_found
from backend.tables import Job, JobState


def get_dispatcher(request: Request) -> queue.Dispatcher:
    dispatcher = getattr(request.app.state, "dispatcher", None)
    if dispatcher is None:
        dispatcher = queue.dispatcher_from_settings(request.app.state.settings)
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
    # The broker was unreachable when it was sent: it stays queued and is sent again later.
    awaiting_dispatch: bool = False

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
            awaiting_dispatch=job.state == JobState.queued and job.dispatch_after is not None,
        )


def send(session: Session, job: Job, dispatcher: Any) -> Job:
    """Send a committed job (``backend.dispatch``): the job after, queued either way.

    Only the first send happens here (its backoff is the first step, 1 s); the sweeper's
    dispatcher loop sends it later with the configured backoff if the broker was down.
    """
    return dispatch.dispatch(session, job_id=job.id, dispatcher=dispatcher)


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
