"""The Celery application of the reconstruction workers (``celery -A worker.celery_app worker``).

Configured from the one settings object (``HAMMURABI_*``, ``backend.settings``) through
``backend.queue.celery_config``: acks_late, prefetch 1, time limits, no result backend (the
job row is the result). With no ``HAMMURABI_BROKER_URL`` the broker is the embedded SQLite
one in ``<data_dir>`` (no server). ``hammurabi worker`` runs this with sensible options.

When the worker is ready it removes the work folders of dead attempts (a previous kill -9)
and starts the job sweeper (``backend.sweeper.Sweeper``): at once, then every
``job_sweep_interval_s`` it sends jobs awaiting dispatch and re-sends jobs the broker lost
and jobs whose worker died; every ``maintenance_interval_s`` it removes dead work folders
(abandoned uploads are expired by the service's sweeper, which holds their part files). A pool process that replaces a killed one also removes dead folders.
"""

from __future__ import annotations

import logging
import os
import threading

from celery import Celery, signals
from sqlalchemy.orm import Session, sessionmaker

from backend.db import make_engine, make_sessionmaker
from backend.jobs import remove_dead_work_folders, work_root
from backend.queue import celery_config, dispatcher_from_settings
from backend.settings import Settings, get_settings
from backend.sweeper import Sweeper

log = logging.getLogger("worker.celery_app")

settings: Settings = get_settings()
app = Celery("hammurabi", include=["worker.tasks"])
app.conf.update(celery_config(settings))

_factory_lock = threading.Lock()
_factory: tuple[int, sessionmaker[Session]] | None = None
_sweeper: Sweeper | None = None


def configure(new_settings: Settings) -> None:
    """Use ``new_settings`` in this process (tests, bench); the next session uses them."""
    global settings, _factory
    with _factory_lock:
        settings = new_settings
        _factory = None
    app.conf.update(celery_config(new_settings))


def session_factory() -> sessionmaker[Session]:
    """A session factory for this process (engines are never shared across a fork)."""
    global _factory
    with _factory_lock:
        if _factory is None or _factory[0] != os.getpid():
            engine = make_engine(settings.resolved_database_url)
            _factory = (os.getpid(), make_sessionmaker(engine))
        return _factory[1]


def remove_dead_folders() -> None:
    """Remove the work folders of attempts whose process is gone (never a live one's)."""
    try:
        remove_dead_work_folders(
            work_root(), unowned_older_than_s=float(settings.job_time_limit_s) + 600
        )
    except OSError:
        log.exception("could not remove the work folders of dead attempts")


@signals.worker_process_init.connect
def _after_a_pool_process_died(**_kwargs) -> None:
    # A new pool process starts at start-up and whenever one was killed: clean up after it.
    remove_dead_folders()


@signals.worker_ready.connect
def _start_sweeper(**_kwargs) -> None:
    global _sweeper
    remove_dead_folders()
    if _sweeper is None:
        _sweeper = Sweeper(
            session_factory(),
            dispatcher_from_settings(settings),
            settings,
            expire_uploads=False,  # the service's sweeper does: it holds the part files
        ).start()
        log.info(
            "job sweeper started (every %.0f s; running jobs stale after %.0f s)",
            settings.job_sweep_interval_s,
            settings.job_stale_after_s,
        )


@signals.worker_shutdown.connect
def _stop_sweeper(**_kwargs) -> None:
    if _sweeper is not None:
        _sweeper.stop()
