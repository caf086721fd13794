"""The one settings object of the library service (env prefix ``HAMMURABI_``).

Every knob the backend (and the worker, which imports this module) reads lives here.
Values come from the environment or a ``.env`` file; see docs/admin.md for the table.

Secrets: in ``production`` the service refuses to start without ``HAMMURABI_SECRET_KEY``
(and refuses well-known placeholder values); in ``development``/``test`` a random secret is
generated once and kept in ``<data_dir>/secret_key`` so sessions survive restarts.
"""

from __future__ import annotations

import os
import secrets
from functools import cached_property
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

_PLACEHOLDER_SECRETS = {"", "changeme", "change-me", "secret", "changethis", "dev", "development"}
_MIN_SECRET_CHARS = 32


class Settings(BaseSettings):
    """Configuration of the library service; construct once, pass explicitly."""

    model_config = SettingsConfigDict(
        env_prefix="HAMMURABI_", env_file=".env", extra="ignore", frozen=True
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

    # HTTP
    cors_allow_origins: list[str] = ["*"]
    frontend_dist: Path | None = Field(
        default=None, description="built frontend served at /; default frontend/dist if present"
    )
    api_prefix: str = "/api/v1"

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
    def _refuse_default_secrets_in_production(self) -> Settings:
        if self.environment == "production":
            value = self.secret_key.get_secret_value() if self.secret_key else ""
            if value.strip().lower() in _PLACEHOLDER_SECRETS:
                raise ValueError(
                    "HAMMURABI_SECRET_KEY must be set to a random value in production "
                    '(e.g. python -c "import secrets; print(secrets.token_urlsafe(48))")'
                )
            if len(value) < _MIN_SECRET_CHARS:
                raise ValueError(
                    f"HAMMURABI_SECRET_KEY is too short ({len(value)} chars, "
                    f"need at least {_MIN_SECRET_CHARS})"
                )
        return self

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
        if len(value) >= _MIN_SECRET_CHARS:
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
