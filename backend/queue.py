"""The broker side of the job queue: which broker, Celery's configuration, sending by name.

The database is the source of truth for jobs (``backend.jobs``); the broker only carries
"run job N now". This module knows nothing of job rows: ``backend.dispatch`` decides what a
send means for a job, ``backend.sweeper`` finds the jobs the broker lost. Layers (checked by
import-linter): sweeper → dispatch → jobs → queue.

Embedded default: with no ``HAMMURABI_BROKER_URL`` the broker is kombu's SQLAlchemy
transport on ``<data_dir>/broker.sqlite`` (no server). No worker code is imported here: the
library sends tasks by name.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

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
        # time limit so a long job is never run twice; dead workers are found by the sweeper
        # (backend.sweeper: dead owner process or stale heartbeat) within seconds.
        config["broker_transport_options"] = {"visibility_timeout": hard_s + 600}
    if is_embedded(url):
        # The embedded transports have no broadcast: no remote control or events.
        config["worker_enable_remote_control"] = False
        config["worker_send_task_events"] = False
    return config


class Dispatcher(Protocol):
    """Anything that publishes a task by name (Celery's ``send_task`` signature)."""

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
        # A short publish retry: a dead broker must not hang the request; the job waits
        # for the dispatcher loop instead (backend.dispatch).
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
    return CeleryDispatcher(broker_url=broker_url(settings), queue=settings.job_queue)
