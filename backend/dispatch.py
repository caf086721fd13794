"""Handing jobs to the broker: the ONE send path, with ONE policy for a broker outage.

Every send goes through :func:`dispatch`: the API (a completed upload, a retry), the worker
(the tablet's registration after its faces) and the sweeper (re-sends). The policy:

- the broker took the message: ``backend.jobs.mark_dispatched`` (``enqueued_at`` set);
- it did not (any transport error, after the dispatcher's own short publish retry): the
  job STAYS QUEUED, marked *awaiting dispatch* (``backend.jobs.mark_awaiting_dispatch``)
  with a backoff of ``min(max, 1 s · 2^(failures-1))``; :func:`dispatch_due` (run by the
  sweeper every ``job_sweep_interval_s``) sends it once due. A broker outage never fails a
  job; the caller gets the queued job back (the API answers 201 as usual).

A duplicate message is harmless: the worker's claim is a compare-and-set on the job row.
"""

from __future__ import annotations

import logging
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from backend import jobs
from backend.queue import Dispatcher
from backend.tables import Job, JobState

log = logging.getLogger("backend.dispatch")

BACKOFF_FIRST_S = 1.0
# A sender holds a due job this long before another may try it (its send is under way).
SEND_HOLD_S = 30.0


def backoff_s(failures: int, *, max_s: float) -> float:
    """Seconds before the next send after ``failures`` consecutive failed sends."""
    if failures < 1:
        return 0.0
    return min(max_s, BACKOFF_FIRST_S * 2.0 ** min(failures - 1, 30))


def dispatch(
    session: Session, *, job_id: int, dispatcher: Dispatcher, backoff_max_s: float = 60.0
) -> Job:
    """Send queued job ``job_id`` to the workers (by task name); return the job row after.

    Call only after the job row is committed (a fast worker must find it). Never raises for
    a broker outage: the job is left awaiting dispatch (module docstring).
    """
    job = session.get(Job, job_id, populate_existing=True)
    if job is None:
        raise LookupError(f"job_id: no job {job_id}")
    if job.state != JobState.queued:
        return job  # taken or finished meanwhile: nothing to send
    name, task_id = jobs.TASK_BY_KIND[job.kind], jobs.task_id(job)
    failures = job.dispatch_failures or 0
    session.rollback()  # no transaction held while talking to the broker
    try:
        dispatcher.send_task(name, args=[job_id], task_id=task_id)
    except Exception as exc:  # any broker/transport failure: the same policy for all
        wait_s = backoff_s(failures + 1, max_s=backoff_max_s)
        log.warning(
            "job %s: the job queue is unreachable (%s: %s); stays queued, next send in %.0f s",
            job_id,
            type(exc).__name__,
            exc,
            wait_s,
        )
        return jobs.mark_awaiting_dispatch(session, job_id=job_id, retry_in_s=wait_s)
    return jobs.mark_dispatched(session, job_id=job_id)


def dispatch_due(
    session: Session,
    dispatcher: Dispatcher,
    *,
    backoff_max_s: float,
    now: datetime | None = None,
    limit: int = 100,
) -> list[int]:
    """Send the jobs awaiting dispatch whose backoff has passed; the ids sent successfully.

    Each is first taken with a compare-and-set (:func:`backend.jobs.take_due_dispatch`), so
    two sweepers never send the same job in one period.
    """
    now = now or jobs.now_utc()
    due = session.scalars(
        select(Job.id)
        .where(Job.state == JobState.queued, Job.dispatch_after <= now)
        .order_by(Job.dispatch_after, Job.id)
        .limit(limit)
    ).all()
    session.rollback()
    sent = []
    for job_id in due:
        if not jobs.take_due_dispatch(session, job_id=job_id, now=now, hold_s=SEND_HOLD_S):
            continue
        job = dispatch(session, job_id=job_id, dispatcher=dispatcher, backoff_max_s=backoff_max_s)
        if job.dispatch_after is None:
            sent.append(job_id)
        else:
            break  # the broker is still down: the others wait for their own backoff
    if sent:
        log.warning("dispatcher: sent %d jobs that were awaiting dispatch: %s", len(sent), sent)
    return sent


def resend(session: Session, *, job_id: int, dispatcher: Dispatcher, backoff_max_s: float) -> bool:
    """Send again a job the sweeper found lost (already claimed by it); True if sent."""
    job = dispatch(session, job_id=job_id, dispatcher=dispatcher, backoff_max_s=backoff_max_s)
    return job.dispatch_after is None
