"""SQLAlchemy 2 tables of the library (typed ORM). Pydantic schemas live in schemas.py.

Search helpers that are not ORM columns (SQLite FTS5 table ``tablets_fts`` and its triggers,
PostgreSQL ``tablets.search_vector`` + GIN index) are created by the initial migration and
used only by :mod:`backend.search`.
"""

from __future__ import annotations

import enum
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy import Enum as SAEnum
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator):
    """A timestamp that is always read back as an aware datetime in UTC.

    SQLite keeps no offset (it returns naive datetimes) and PostgreSQL returns the session's
    time zone: stored values are UTC (naive ones are taken as UTC), read values get
    ``tzinfo=UTC``, so every API answer says ``+00:00`` whatever the database.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if isinstance(value, datetime):
            value = value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
            if dialect.name == "sqlite":
                value = value.replace(tzinfo=None)  # stored as text: one format for all rows
        return value

    def process_result_value(self, value, dialect):
        if isinstance(value, datetime):
            return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)
        return value


# SQLite hands a deleted row's id (the largest) to the next row unless the table is
# AUTOINCREMENT; ids name stable URLs (/tablets/7526), so they are never reused (0009).
NEVER_REUSE_IDS = {"sqlite_autoincrement": True}


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON, datetime: UTCDateTime()}


def _enum(cls: type[enum.Enum], name: str) -> SAEnum:
    # Stored as plain strings (VARCHAR + CHECK) so adding a value never needs a PG ALTER TYPE.
    return SAEnum(
        cls,
        name=name,
        native_enum=False,
        create_constraint=True,
        length=16,
        values_callable=lambda members: [m.value for m in members],
        validate_strings=True,
    )


class Role(enum.StrEnum):
    admin = "admin"
    staff = "staff"
    reader = "reader"


class UploadState(enum.StrEnum):
    open = "open"
    complete = "complete"
    failed = "failed"


class JobKind(enum.StrEnum):
    reconstruct = "reconstruct"
    derive = "derive"
    register = "register"


class JobState(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"


class Institution(Base):
    __tablename__ = "institutions"
    __table_args__ = NEVER_REUSE_IDS

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    # Defaults for the institution's tablets and models that set none (backend.licences).
    licence: Mapped[str | None] = mapped_column(String(300))
    attribution: Mapped[str | None] = mapped_column(String(500))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class User(Base):
    __tablename__ = "users"
    __table_args__ = NEVER_REUSE_IDS

    id: Mapped[int] = mapped_column(primary_key=True)
    email: Mapped[str] = mapped_column(String(320), unique=True)
    password_hash: Mapped[str | None] = mapped_column(String(200))
    role: Mapped[Role] = mapped_column(_enum(Role, "user_role"), default=Role.reader)
    institution_id: Mapped[int | None] = mapped_column(
        ForeignKey("institutions.id", ondelete="SET NULL"), index=True
    )
    is_active: Mapped[bool] = mapped_column(Boolean, default=True)
    # In every session cookie; bumped by logout, a password change and disabling the account,
    # which makes every cookie signed before unusable (crud.revoke_sessions).
    session_version: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    institution: Mapped[Institution | None] = relationship(lazy="joined")


class ApiToken(Base):
    __tablename__ = "api_tokens"
    __table_args__ = NEVER_REUSE_IDS

    id: Mapped[int] = mapped_column(primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(200))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)  # sha256 hex of the secret
    prefix: Mapped[str] = mapped_column(String(16))  # first characters, for display
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    last_used_at: Mapped[datetime | None]
    revoked_at: Mapped[datetime | None]


class Tablet(Base):
    __tablename__ = "tablets"

    id: Mapped[int] = mapped_column(primary_key=True)
    designation: Mapped[str] = mapped_column(String(300))
    # Unique per institution, not library-wide (crud.create_tablet, migration 0003_p_number).
    p_number: Mapped[str | None] = mapped_column(String(32), index=True)
    museum_no: Mapped[str | None] = mapped_column(String(300))
    collection: Mapped[str | None] = mapped_column(String(300))
    owner: Mapped[str | None] = mapped_column(String(300))
    excavation_no: Mapped[str | None] = mapped_column(String(300))
    period: Mapped[str | None] = mapped_column(String(200))
    provenience: Mapped[str | None] = mapped_column(String(200))
    genre: Mapped[str | None] = mapped_column(String(200))
    subgenre: Mapped[str | None] = mapped_column(String(300))
    language: Mapped[str | None] = mapped_column(String(200))
    material: Mapped[str | None] = mapped_column(String(200))
    object_type: Mapped[str | None] = mapped_column(String(200))
    height_mm: Mapped[float | None] = mapped_column(Float)
    width_mm: Mapped[float | None] = mapped_column(Float)
    thickness_mm: Mapped[float | None] = mapped_column(Float)
    primary_publication: Mapped[str | None] = mapped_column(Text)
    notes: Mapped[str | None] = mapped_column(Text)
    # The transliteration in ATF (backend.atf parses it; annotations refer to its signs).
    atf: Mapped[str | None] = mapped_column(Text)
    # A Creative Commons / RightsStatements.org URI and a credit line; None: the institution's.
    licence: Mapped[str | None] = mapped_column(String(300))
    attribution: Mapped[str | None] = mapped_column(String(500))
    institution_id: Mapped[int | None] = mapped_column(
        ForeignKey("institutions.id", ondelete="SET NULL"), index=True
    )
    is_public: Mapped[bool] = mapped_column(Boolean, default=False, index=True)
    # Maintained flag: set by crud.refresh_has_3d whenever a model of the tablet is created
    # or deleted (a flag, not a subquery, so the has_3d facet stays an index scan).
    has_3d: Mapped[bool] = mapped_column(Boolean, default=False, index=True)
    extra: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)

    institution: Mapped[Institution | None] = relationship(lazy="joined")

    __table_args__ = (
        Index("ix_tablets_period", "period"),
        Index("ix_tablets_provenience", "provenience"),
        Index("ix_tablets_genre", "genre"),
        Index("ix_tablets_collection", "collection"),
        Index("ix_tablets_language", "language"),
        Index("ix_tablets_designation", "designation"),
        Index("uq_tablets_institution_p_number", "institution_id", "p_number", unique=True),
        Index(
            "uq_tablets_p_number_no_institution",
            "p_number",
            unique=True,
            sqlite_where=text("institution_id IS NULL"),
            postgresql_where=text("institution_id IS NULL"),
        ),
        NEVER_REUSE_IDS,
    )


class Upload(Base):
    __tablename__ = "uploads"

    id: Mapped[str] = mapped_column(String(36), primary_key=True)  # uuid4 string
    tablet_id: Mapped[int] = mapped_column(ForeignKey("tablets.id", ondelete="CASCADE"), index=True)
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    filename: Mapped[str] = mapped_column(String(500))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    ranges: Mapped[list[Any]] = mapped_column(JSON, default=list)  # [[start, end), ...] received
    state: Mapped[UploadState] = mapped_column(
        _enum(UploadState, "upload_state"), default=UploadState.open
    )
    sha256: Mapped[str | None] = mapped_column(String(64))
    storage_key: Mapped[str | None] = mapped_column(String(500))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)
    # Optimistic lock: concurrent chunk requests merge their ranges without losing one
    # (an UPDATE of a stale revision raises StaleDataError and is retried; backend.uploads).
    revision: Mapped[int] = mapped_column(Integer, default=1, server_default="1")

    __mapper_args__ = {"version_id_col": revision}


class Scan(Base):
    __tablename__ = "scans"
    __table_args__ = NEVER_REUSE_IDS

    id: Mapped[int] = mapped_column(primary_key=True)
    tablet_id: Mapped[int] = mapped_column(ForeignKey("tablets.id", ondelete="CASCADE"), index=True)
    face: Mapped[str] = mapped_column(String(32))
    scan_uid: Mapped[str | None] = mapped_column(String(100), unique=True)  # manifest scan.id
    bundle_key: Mapped[str] = mapped_column(String(500))
    bundle_sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    manifest: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = NEVER_REUSE_IDS

    id: Mapped[int] = mapped_column(primary_key=True)
    scan_id: Mapped[int | None] = mapped_column(
        ForeignKey("scans.id", ondelete="CASCADE"), index=True
    )
    tablet_id: Mapped[int] = mapped_column(ForeignKey("tablets.id", ondelete="CASCADE"), index=True)
    kind: Mapped[JobKind] = mapped_column(_enum(JobKind, "job_kind"), default=JobKind.reconstruct)
    state: Mapped[JobState] = mapped_column(
        _enum(JobState, "job_state"), default=JobState.queued, index=True
    )
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(100))
    timings: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    error: Mapped[str | None] = mapped_column(Text)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    enqueued_at: Mapped[datetime | None]
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    heartbeat_at: Mapped[datetime | None]
    # The process of the current attempt (backend.jobs.process_owner): tells a dead attempt
    # from a live one when Celery redelivers after a kill.
    claimed_by: Mapped[str | None] = mapped_column(String(200))
    # A queued job the broker could not take: sent again from dispatch_after (backoff).
    dispatch_failures: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    dispatch_after: Mapped[datetime | None] = mapped_column(index=True)
    # No FK to models: models.job_id already points here; a cycle would complicate deletes.
    model_id: Mapped[int | None] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Model(Base):
    __tablename__ = "models"

    id: Mapped[int] = mapped_column(primary_key=True)
    scan_id: Mapped[int | None] = mapped_column(
        ForeignKey("scans.id", ondelete="CASCADE"), index=True
    )
    tablet_id: Mapped[int] = mapped_column(ForeignKey("tablets.id", ondelete="CASCADE"), index=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), unique=True)
    version: Mapped[int] = mapped_column(Integer)
    storage_prefix: Mapped[str] = mapped_column(String(500))
    report: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    assets: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    # None: the tablet's (a model made elsewhere may carry its maker's licence and credit).
    licence: Mapped[str | None] = mapped_column(String(300))
    attribution: Mapped[str | None] = mapped_column(String(500))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    # Loaded on use: the licence that applies falls back to the tablet's (backend.licences).
    tablet: Mapped[Tablet] = relationship(lazy="select")

    __table_args__ = (
        UniqueConstraint("scan_id", "version", name="uq_models_scan_version"),
        NEVER_REUSE_IDS,
    )


class Annotation(Base):
    """A region of a model version tied to a sign of the text (a W3C Web Annotation).

    The region is a polygon in the model's scan frame (mm) and, when known, the same polygon
    in the image grid (pixels) of ``image_face``'s image; backend.annotations builds the
    JSON-LD. It belongs to one model version: a new reconstruction starts without them.
    """

    __tablename__ = "annotations"
    __table_args__ = NEVER_REUSE_IDS

    id: Mapped[int] = mapped_column(primary_key=True)
    model_id: Mapped[int] = mapped_column(ForeignKey("models.id", ondelete="CASCADE"), index=True)
    # Denormalised from the model: the tablet's listing and its access check need no join.
    tablet_id: Mapped[int] = mapped_column(ForeignKey("tablets.id", ondelete="CASCADE"), index=True)
    creator_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    reference: Mapped[str] = mapped_column(String(40))  # normalised: "o 2 3"
    reading: Mapped[str | None] = mapped_column(String(200))
    comment: Mapped[str | None] = mapped_column(Text)
    polygon_mm: Mapped[list[Any]] = mapped_column(JSON, default=list)  # [[x, y, z], ...]
    polygon_px: Mapped[list[Any] | None] = mapped_column(JSON)  # [[col, row], ...]
    image_face: Mapped[str | None] = mapped_column(String(32))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(default=utcnow, onupdate=utcnow)

    creator: Mapped[User | None] = relationship(lazy="joined")
    model: Mapped[Model] = relationship(lazy="joined")
