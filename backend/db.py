"""Engine, sessions and migrations for SQLite (default) and PostgreSQL.

SQLite: WAL journal, foreign keys on, a busy timeout so concurrent writers wait instead of
failing. PostgreSQL: ``postgresql+psycopg://`` URLs with a connection pool.

The places that commit are :func:`session_scope` (the CLI, workers) and the API's
``SessionDep`` (backend.api.deps): crud functions only add/flush.

Concurrency of the web service (issue 16: it deadlocked). A request's sync dependencies and
route each run in their own hop to the thread pool, and a session keeps its connection (and
on SQLite the write lock, on PostgreSQL row locks) between hops. If more requests hold
connections than the pool has, threads wait for connections while the connections' owners
wait for threads. So the service admits at most ``http_threads`` requests with a session
at once (``backend.api.deps.SessionGate``, awaited on the event loop, where waiting holds
nothing), the thread pool has ``http_threads`` threads and the pool ``http_threads + POOL_MARGIN``
connections (:func:`server_pool_size`): a thread never waits for a connection, and a
request holding a lock always gets a thread, because at most ``http_threads - 1`` others
can be waiting for that lock in threads.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

from pydantic import Field
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from backend.settings import Settings

ALEMBIC_DIR = Path(__file__).resolve().parent / "alembic"

MAX_ID = 2**31 - 1
"""The largest row id: ids are INTEGER columns, 32-bit on PostgreSQL (64-bit on SQLite)."""

RowId = Annotated[int, Field(ge=1, le=MAX_ID)]
"""An id that can name a row on either database: path, query and body fields use it, so an
out-of-range id is a 422 naming the field, never an overflow inside the driver (a 500)."""

POOL_MARGIN = 10
"""Connections beyond the admitted requests, for code that opens a second session while its
request holds one (uploads.record_range opens its own)."""

# SQLite's busy timeout (s): how long a writer waits for the write lock. Writers hold it
# only while running in a thread (see the module docstring), so waits are short.
SQLITE_BUSY_TIMEOUT_S = 30


def is_sqlite(url: str) -> bool:
    return make_url(url).get_backend_name() == "sqlite"


def server_pool_size(http_threads: int) -> int:
    """Connections of the web service's pool for ``http_threads`` admitted requests."""
    return http_threads + POOL_MARGIN


def make_engine(url: str, *, pool_size: int | None = None) -> Engine:
    """An engine for ``url`` with the pragmas/pool settings the service relies on.

    ``pool_size``: a fixed pool of that many connections (the web service:
    :func:`server_pool_size`); default 20 plus 20 overflow (CLI, workers, tests).
    """
    pool = (
        {"pool_size": 20, "max_overflow": 20}
        if pool_size is None
        else {"pool_size": pool_size, "max_overflow": 0}
    )
    if is_sqlite(url):
        database = make_url(url).database
        if database and database != ":memory:":
            Path(database).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(
            url,
            connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_S},
            **pool,
        )

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection, _record):  # pragma: no branch
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.close()

        return engine
    return create_engine(url, **pool, pool_pre_ping=True)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    # expire_on_commit=False: routes serialise objects after the commit in session_scope.
    return sessionmaker(bind=engine, expire_on_commit=False, autoflush=True)


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session that commits when the block ends normally and rolls back otherwise."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def alembic_config(url: str):
    """Alembic configuration built in code (no alembic.ini needed)."""
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(ALEMBIC_DIR))
    # '%' is alembic's interpolation character; URLs may contain it (escaped passwords).
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def migrate(url: str, revision: str = "head") -> None:
    """Bring the database at ``url`` to ``revision`` (alembic upgrade)."""
    from alembic import command

    if is_sqlite(url):
        database = make_url(url).database
        if database and database != ":memory:":
            Path(database).parent.mkdir(parents=True, exist_ok=True)
    command.upgrade(alembic_config(url), revision)


def database_url(settings: Settings) -> str:
    return settings.resolved_database_url
