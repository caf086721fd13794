"""Fixtures for the library service, for every backend test (yours too: reuse them).

- ``db_url``: a migrated, empty database, parametrized over ``sqlite`` and ``postgresql``
  (the latter marked ``postgres``). SQLite: a copy of a migrated template file per test.
  PostgreSQL: one throwaway database per test session (unique name, dropped at the end),
  tables truncated before each test.
- ``sqlite_url`` / ``sqlite_app``: SQLite only, for tests that need no PostgreSQL run.
- ``settings`` / ``app`` / ``client``: ``create_app(settings)`` on that database, data and
  storage under ``tmp_path``; ``client`` is a ``fastapi.testclient.TestClient``.
- ``world``: two institutions, a user of every role with an API token, and three tablets
  (public and private of institution A, private of B). ``world.headers(role)`` gives the
  ``Authorization`` header of a role (``{}`` for anonymous); roles are ``ROLES``.
"""

from __future__ import annotations

import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import psycopg
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text
from sqlalchemy.orm import Session

from backend import crud, security
from backend.db import make_engine, make_sessionmaker, migrate, session_scope
from backend.main import create_app
from backend.settings import Settings
from backend.tables import Base, Job, JobKind, JobState, Model, Role, Scan, Tablet

PG_ADMIN_DSN = "host=127.0.0.1 port=5432 user=postgres dbname=postgres"
PG_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
ROLES = ("anonymous", "reader", "staff_own", "staff_other", "admin")
PASSWORD = "correct horse battery staple"
SECRET_KEY = "test-secret-key-" + "x" * 40


@pytest.fixture(scope="session")
def password_hash() -> str:
    # argon2 is slow on purpose; hash the shared test password once per session.
    return security.hash_password(PASSWORD)


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sqlite_template") / "template.db"
    migrate(f"sqlite:///{path}")
    return path


@pytest.fixture(scope="session")
def pg_database() -> Iterator[str]:
    name = f"hammurabi_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(PG_ADMIN_DSN, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    url = PG_URL.format(name=name)
    try:
        migrate(url)
        yield url
    finally:
        with psycopg.connect(PG_ADMIN_DSN, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def _sqlite_copy(template: Path, tmp_path: Path) -> str:
    path = tmp_path / "hammurabi.db"
    shutil.copyfile(template, path)
    return f"sqlite:///{path}"


def _pg_truncated(url: str) -> str:
    engine = make_engine(url)
    tables = ", ".join(t.name for t in Base.metadata.sorted_tables)
    with engine.begin() as conn:
        conn.execute(text(f"TRUNCATE {tables} RESTART IDENTITY CASCADE"))
    engine.dispose()
    return url


@pytest.fixture
def sqlite_url(sqlite_template, tmp_path) -> str:
    return _sqlite_copy(sqlite_template, tmp_path)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request, sqlite_template, tmp_path) -> str:
    if request.param == "sqlite":
        return _sqlite_copy(sqlite_template, tmp_path)
    return _pg_truncated(request.getfixturevalue("pg_database"))


def make_settings(db_url: str, tmp_path: Path, **overrides) -> Settings:
    values = dict(
        environment="test",
        data_dir=tmp_path / "var",
        database_url=db_url,
        secret_key=SECRET_KEY,
        storage_dir=tmp_path / "storage",
        frontend_dist=tmp_path / "no-frontend",
    )
    values.update(overrides)
    return Settings(_env_file=None, **values)


@pytest.fixture
def settings(db_url, tmp_path) -> Settings:
    return make_settings(db_url, tmp_path)


@pytest.fixture
def app(settings):
    app = create_app(settings)
    yield app
    app.state.engine.dispose()


@pytest.fixture
def sqlite_app(sqlite_url, tmp_path):
    """The app on SQLite only, for tests whose outcome cannot depend on the database."""
    app = create_app(make_settings(sqlite_url, tmp_path))
    yield app
    app.state.engine.dispose()


@pytest.fixture
def client(app) -> Iterator[TestClient]:
    with TestClient(app) as client:
        yield client


@dataclass
class World:
    """Users of every role (with tokens) and tablets of two institutions."""

    sessionmaker: object
    settings: Settings | None = None
    institution_a: int = 0
    institution_b: int = 0
    users: dict[str, int] = field(default_factory=dict)  # role -> user id
    emails: dict[str, str] = field(default_factory=dict)
    tokens: dict[str, str] = field(default_factory=dict)  # role -> API token secret
    public_a: int = 0
    private_a: int = 0
    private_b: int = 0

    @contextmanager
    def session(self) -> Iterator[Session]:
        with session_scope(self.sessionmaker) as session:
            yield session

    def headers(self, role: str) -> dict[str, str]:
        if role == "anonymous":
            return {}
        return {"Authorization": f"Bearer {self.tokens[role]}"}

    def new_tablet(self, *, institution: str = "a", is_public: bool = False, **fields) -> int:
        """A fresh tablet of institution ``a`` or ``b``; returns its id."""
        institution_id = {"a": self.institution_a, "b": self.institution_b, None: None}[institution]
        fields.setdefault("designation", f"Test {uuid.uuid4().hex[:8]}")
        with self.session() as session:
            tablet = crud.create_tablet(
                session, fields={**fields, "is_public": is_public}, institution_id=institution_id
            )
            return tablet.id

    def new_scan(self, tablet_id: int, *, face: str = "obverse") -> int:
        """A scan row (no bundle stored) of ``tablet_id``; returns its id."""
        with self.session() as session:
            scan = Scan(
                tablet_id=tablet_id,
                face=face,
                scan_uid=uuid.uuid4().hex,
                bundle_key=f"bundles/{uuid.uuid4().hex}.zip",
                bundle_sha256="0" * 64,
                size_bytes=1,
                manifest={},
                user_id=self.users["staff_own"],
            )
            session.add(scan)
            session.flush()
            return scan.id

    def new_job(self, tablet_id: int, *, scan_id: int | None = None, state=JobState.queued) -> int:
        with self.session() as session:
            job = Job(tablet_id=tablet_id, scan_id=scan_id, kind=JobKind.reconstruct, state=state)
            session.add(job)
            session.flush()
            return job.id

    def new_model(
        self, tablet_id: int, *, assets: dict | None = None, report: dict | None = None
    ) -> int:
        """A model row (with its scan and succeeded job) of ``tablet_id``; returns its id."""
        scan_id = self.new_scan(tablet_id)
        job_id = self.new_job(tablet_id, scan_id=scan_id, state=JobState.succeeded)
        with self.session() as session:
            model = Model(
                tablet_id=tablet_id,
                scan_id=scan_id,
                job_id=job_id,
                version=1,
                storage_prefix=f"models/{uuid.uuid4().hex}",
                report=report or {},
                assets=assets or {},
            )
            session.add(model)
            session.flush()
            return model.id


def build_world(sessionmaker, password_hash: str, settings: Settings | None = None) -> World:
    world = World(sessionmaker=sessionmaker, settings=settings)
    with session_scope(sessionmaker) as session:
        a = crud.get_or_create_institution(session, name="Museum A")
        b = crud.get_or_create_institution(session, name="Museum B")
        world.institution_a, world.institution_b = a.id, b.id
        specs = {
            "reader": (Role.reader, None),
            "staff_own": (Role.staff, a.id),
            "staff_other": (Role.staff, b.id),
            "admin": (Role.admin, None),
        }
        for role, (db_role, institution_id) in specs.items():
            email = f"{role.replace('_', '-')}@example.org"
            user = crud.create_user(
                session, email=email, role=db_role, institution_id=institution_id
            )
            user.password_hash = password_hash
            _token, secret = crud.create_token(session, user=user, name=f"{role} token")
            world.users[role], world.emails[role], world.tokens[role] = user.id, email, secret
        tablets = [
            Tablet(designation="Public A", p_number="P000001", is_public=True, institution_id=a.id),
            Tablet(designation="Private A", p_number="P000002", institution_id=a.id),
            Tablet(designation="Private B", p_number="P000003", institution_id=b.id),
        ]
        session.add_all(tablets)
        session.flush()
        world.public_a, world.private_a, world.private_b = (t.id for t in tablets)
    return world


@pytest.fixture
def world(app, password_hash) -> World:
    return build_world(app.state.sessionmaker, password_hash, app.state.settings)


@pytest.fixture
def db_session(app) -> Iterator[Session]:
    """A session on the app's database, committed at the end of the test."""
    with session_scope(make_sessionmaker(app.state.engine)) as session:
        yield session
