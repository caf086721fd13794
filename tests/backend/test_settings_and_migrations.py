"""Settings refuse default secrets in production; the migration matches the tables."""

from __future__ import annotations

import secrets
import stat

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from pydantic import ValidationError
from sqlalchemy import inspect

from backend.db import make_engine
from backend.settings import Settings
from backend.tables import Base


def _settings(**values) -> Settings:
    return Settings(_env_file=None, **values)


@pytest.mark.parametrize("secret", [None, "changeme", "short-secret"])
def test_production_refuses_missing_or_weak_secret(tmp_path, secret):
    with pytest.raises(ValidationError, match="HAMMURABI_SECRET_KEY"):
        _settings(environment="production", data_dir=tmp_path, secret_key=secret)


def test_production_uses_the_configured_secret(tmp_path):
    secret = secrets.token_urlsafe(48)
    settings = _settings(
        environment="production",
        data_dir=tmp_path,
        secret_key=secret,
        public_url="https://library.example.org",
    )
    assert settings.signing_secret == secret
    assert settings.cookie_secure is True
    assert not (tmp_path / "secret_key").exists()


@pytest.mark.parametrize(
    "url", ["library.example.org", "ftp://library.example.org", "https://", "https://a.org/?x=1"]
)
def test_public_url_must_be_an_http_url(url):
    with pytest.raises(ValidationError, match="HAMMURABI_PUBLIC_URL"):
        _settings(public_url=url)


def test_public_url_default_outside_production():
    assert _settings().resolved_public_url == "http://127.0.0.1:8000"
    assert _settings(public_url="https://a.org/x/").resolved_public_url == "https://a.org/x"


def test_development_secret_is_generated_once_and_private(tmp_path):
    first = _settings(data_dir=tmp_path).signing_secret
    second = _settings(data_dir=tmp_path).signing_secret
    assert first == second and len(first) >= 32
    mode = stat.S_IMODE((tmp_path / "secret_key").stat().st_mode)
    assert mode == 0o600


def test_environment_variables_and_defaults(tmp_path, monkeypatch):
    monkeypatch.setenv("HAMMURABI_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("HAMMURABI_SEARCH_MAX_PAGE_SIZE", "50")
    settings = _settings()
    assert settings.search_max_page_size == 50
    assert settings.resolved_database_url == f"sqlite:///{(tmp_path / 'hammurabi.db').resolve()}"
    assert settings.resolved_storage_dir == tmp_path / "storage"


def test_migrations_match_the_tables(db_url):
    """Autogenerate finds nothing to add: tables.py and the migrations agree."""
    engine = make_engine(db_url)
    with engine.connect() as connection:
        diffs = compare_metadata(MigrationContext.configure(connection), Base.metadata)
        table_names = set(inspect(connection).get_table_names())
    engine.dispose()
    # search structures live outside the ORM metadata on purpose (see backend.search)
    diffs = [d for d in diffs if "tablets_fts" not in str(d) and "search_vector" not in str(d)]
    assert diffs == []
    assert {t.name for t in Base.metadata.sorted_tables} <= table_names


def test_sqlite_is_in_wal_mode_with_foreign_keys(sqlite_url):
    engine = make_engine(sqlite_url)
    with engine.connect() as connection:
        assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    engine.dispose()
