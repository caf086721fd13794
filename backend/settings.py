"""The one settings object of the library service (env prefix ``HAMMURABI_``).

Every knob the backend (and the worker, which imports this module) reads lives here.
Values come from the environment or a ``.env`` file; see docs/admin.md for the table.

Secrets: in ``production`` the service refuses to start without ``HAMMURABI_SECRET_KEY``, and
refuses any secret it holds (the key, the S3 secret, the database password) that is a known
placeholder, is derived from one (case, punctuation, look-alike digits, repetition, reversal),
or has too little estimated entropy (:func:`backend.secret_policy.secret_problem`). In ``development``/``test`` a
random secret is generated once and kept in ``<data_dir>/secret_key`` so sessions survive
restarts.
"""

from __future__ import annotations

import os
import secrets
from functools import cached_property
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit, urlunsplit

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError

from backend.secret_policy import GENERATE_HINT, MIN_SECRET_CHARS, secret_problem

DEV_PUBLIC_URL = "http://127.0.0.1:8000"  # `hammurabi serve` sets its own host and port


class Settings(BaseSettings):
    """Configuration of the library service; construct once, pass explicitly."""

    model_config = SettingsConfigDict(
        env_prefix="HAMMURABI_",
        env_file=".env",
        extra="ignore",
        frozen=True,
        hide_input_in_errors=True,  # a refusal must not print the secrets it refuses
    )

    environment: Literal["development", "test", "production"] = "development"
    data_dir: Path = Path("var")
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL; default sqlite file <data_dir>/hammurabi.db",
    )
    secret_key: SecretStr | None = None

    # web sessions (password login)
    session_cookie_name: str = "hammurabi_session"
    session_max_age_s: int = 14 * 24 * 3600
    session_cookie_secure: bool | None = Field(
        default=None, description="Secure flag of the cookie; default: True in production"
    )
    # login limits (backend.security.LoginLimiter; per server process)
    login_max_attempts_per_account: int = Field(
        default=5, ge=1, description="failed logins of one e-mail per window before 429"
    )
    login_max_attempts_per_address: int = Field(
        default=30, ge=1, description="failed logins from one client address per window"
    )
    login_window_s: float = Field(default=300.0, gt=0, description="sliding window of both")
    password_hash_concurrency: int = Field(
        default=2, ge=1, description="argon2 hashes at once (64 MiB each); the rest wait"
    )

    # HTTP
    public_url: str | None = Field(
        default=None,
        description="the address users reach the library at, e.g. https://library.museum.org "
        "(IIIF ids and every absolute URL start with it, never with the request's Host "
        "header); required in production; elsewhere default http://127.0.0.1:<port>",
    )
    cors_allow_origins: list[str] = ["*"]
    frontend_dist: Path | None = Field(
        default=None, description="built frontend served at /; default frontend/dist if present"
    )
    api_prefix: str = "/api/v1"
    http_threads: int = Field(
        default=40,
        ge=2,
        le=1000,
        description="threads for sync routes per server process; also the requests holding a "
        "database session at once, and (plus 10) the size of the connection pool (backend.db)",
    )

    request_max_body_bytes: int = Field(
        default=4 * 1024 * 1024,
        ge=1024,
        description="largest request body (413 above it; upload chunks have their own limits)",
    )

    # search
    search_max_page_size: int = 200
    search_facet_limit: int = 50

    # storage of bundles and models (used by backend.storage)
    storage_backend: Literal["local", "s3"] = "local"
    storage_dir: Path | None = Field(default=None, description="default <data_dir>/storage")
    s3_endpoint_url: str | None = None
    s3_bucket: str = "hammurabi"
    s3_region: str = "us-east-1"
    s3_access_key_id: str | None = None
    s3_secret_access_key: SecretStr | None = None

    # uploads (used by backend.uploads; docs/admin.md "Upload limits and quotas")
    upload_chunk_size_bytes: int = Field(default=8 * 1024 * 1024, gt=0)
    upload_max_bytes: int = Field(
        default=20 * 1024**3, gt=0, description="largest size_bytes one upload may declare"
    )
    upload_quota_bytes: int = Field(
        default=500 * 1024**3,
        ge=0,
        description="per institution: bytes of its stored scans plus bytes received by its "
        "open uploads; 0 = no quota",
    )
    upload_min_free_bytes: int = Field(
        default=5 * 1024**3, ge=0, description="a chunk that would leave less free disk is 507"
    )
    upload_expire_after_s: float = Field(
        default=7 * 24 * 3600.0,
        gt=0,
        description="an upload left open (or refused) this long is deleted by expire_uploads",
    )

    # jobs (used by backend.jobs and the worker)
    broker_url: str | None = Field(
        default=None,
        description="Celery broker, e.g. redis://redis:6379/0; default: the embedded broker "
        "sqla+sqlite:///<data_dir>/broker.sqlite (no server needed; backend.queue)",
    )
    job_queue: str = "reconstruct"
    job_heartbeat_interval_s: float = Field(
        default=5.0, gt=0, description="a running job's worker refreshes its heartbeat this often"
    )
    job_stale_after_s: float = Field(
        default=15.0,
        gt=0,
        description="a running job without heartbeat this long is taken over (>= 2 heartbeats)",
    )
    job_queued_stale_after_s: float = Field(
        default=600.0, gt=0, description="a queued job not picked up this long is re-sent"
    )
    job_sweep_interval_s: float = Field(default=5.0, gt=0, description="sweeper period")
    job_dispatch_backoff_max_s: float = Field(
        default=60.0, gt=0, description="longest wait between sends of a job the broker refused"
    )
    maintenance_interval_s: float = Field(
        default=3600.0,
        gt=0,
        description="how often the sweeper expires uploads (upload_expire_after_s) and dead work folders",
    )
    job_time_limit_s: float = Field(default=3600.0, gt=0, description="hard limit per task")

    @field_validator("public_url")
    @classmethod
    def _check_public_url(cls, value: str | None) -> str | None:
        if value is None or not value.strip():
            return None
        parts = urlsplit(value.strip())
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(
                f"HAMMURABI_PUBLIC_URL {value!r} is not an http(s) URL with a host, "
                "e.g. https://library.museum.org"
            )
        if parts.query or parts.fragment:
            raise ValueError(f"HAMMURABI_PUBLIC_URL {value!r} must not have a query or fragment")
        return urlunsplit((parts.scheme, parts.netloc, parts.path.rstrip("/"), "", ""))

    @model_validator(mode="after")
    def _check_job_timing(self) -> Settings:
        if self.job_stale_after_s < 2 * self.job_heartbeat_interval_s:
            raise ValueError(
                f"HAMMURABI_JOB_STALE_AFTER_S ({self.job_stale_after_s:g} s) must be at least "
                f"two heartbeats (HAMMURABI_JOB_HEARTBEAT_INTERVAL_S = "
                f"{self.job_heartbeat_interval_s:g} s): a live job would be taken over"
            )
        return self

    @model_validator(mode="after")
    def _production_requirements(self) -> Settings:
        """Every problem at once: weak secrets (backend.secret_policy), no public URL."""
        if self.environment != "production":
            return self
        problems = [
            f"{name} {problem}"
            for name, value in self._held_secrets()
            if (problem := secret_problem(value)) is not None
        ]
        if problems:
            problems[-1] += f" ({GENERATE_HINT})"
        if self.public_url is None:
            problems.append(
                "HAMMURABI_PUBLIC_URL is not set: give the address users reach the library "
                "at, e.g. https://library.museum.org (IIIF ids and links are built from it)"
            )
        if problems:
            raise ValueError("refusing to start in production: " + "; ".join(problems))
        return self

    def _held_secrets(self) -> list[tuple[str, str | None]]:
        """(variable, value) of every secret this object holds; the database password is
        checked only when the URL has one (a local socket may need none)."""
        held = [
            ("HAMMURABI_SECRET_KEY", self.secret_key.get_secret_value() if self.secret_key else "")
        ]
        if self.s3_secret_access_key is not None:
            held.append(
                ("HAMMURABI_S3_SECRET_ACCESS_KEY", self.s3_secret_access_key.get_secret_value())
            )
        if self.database_url:
            try:
                password = make_url(self.database_url).password
            except ArgumentError:
                password = None  # a malformed URL fails clearly when the engine is made
            if password is not None:
                held.append(("the password in HAMMURABI_DATABASE_URL", str(password)))
        return held

    @property
    def resolved_public_url(self) -> str:
        """Base of every absolute URL we hand out, without a trailing slash."""
        return self.public_url if self.public_url is not None else DEV_PUBLIC_URL

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'hammurabi.db').resolve()}"

    @property
    def resolved_storage_dir(self) -> Path:
        return self.storage_dir if self.storage_dir is not None else self.data_dir / "storage"

    @property
    def resolved_frontend_dist(self) -> Path | None:
        if self.frontend_dist is not None:
            return self.frontend_dist
        default = Path(__file__).resolve().parent.parent / "frontend" / "dist"
        return default if default.is_dir() else None

    @property
    def cookie_secure(self) -> bool:
        if self.session_cookie_secure is not None:
            return self.session_cookie_secure
        return self.environment == "production"

    @cached_property
    def signing_secret(self) -> str:
        """The secret that signs session cookies.

        Production: the configured one (validated above). Elsewhere: the configured one, or a
        random one generated once and kept (mode 0600) in ``<data_dir>/secret_key``.
        """
        if self.secret_key is not None and self.secret_key.get_secret_value():
            return self.secret_key.get_secret_value()
        return _load_or_create_dev_secret(self.data_dir / "secret_key")


def _load_or_create_dev_secret(path: Path) -> str:
    if path.exists():
        value = path.read_text().strip()
        if len(value) >= MIN_SECRET_CHARS:
            return value
    path.parent.mkdir(parents=True, exist_ok=True)
    value = secrets.token_urlsafe(48)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(value)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return value


def get_settings() -> Settings:
    """Settings from the environment (the CLI and the worker call this once)."""
    return Settings()
