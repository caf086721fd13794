"""initial tables (all of them) and the full-text search structures

Revision ID: 0001
Revises:
Create Date: 2026-11-21 01:47:20.343024
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


# Text search over these columns (backend.search): SQLite FTS5 external-content table kept in
# sync by triggers; PostgreSQL generated tsvector column with a GIN index.
SEARCH_COLUMNS = (
    "designation",
    "p_number",
    "museum_no",
    "excavation_no",
    "primary_publication",
    "notes",
)


def _create_search_structures() -> None:
    bind = op.get_bind()
    cols = ", ".join(SEARCH_COLUMNS)
    if bind.dialect.name == "sqlite":
        new = ", ".join(f"new.{c}" for c in SEARCH_COLUMNS)
        old = ", ".join(f"old.{c}" for c in SEARCH_COLUMNS)
        op.execute(
            f"CREATE VIRTUAL TABLE tablets_fts USING fts5({cols}, content='tablets', "
            "content_rowid='id', tokenize='unicode61 remove_diacritics 2')"
        )
        op.execute(
            "CREATE TRIGGER tablets_fts_ai AFTER INSERT ON tablets BEGIN "
            f"INSERT INTO tablets_fts(rowid, {cols}) VALUES (new.id, {new}); END"
        )
        op.execute(
            "CREATE TRIGGER tablets_fts_ad AFTER DELETE ON tablets BEGIN "
            f"INSERT INTO tablets_fts(tablets_fts, rowid, {cols}) "
            f"VALUES ('delete', old.id, {old}); END"
        )
        op.execute(
            f"CREATE TRIGGER tablets_fts_au AFTER UPDATE OF {cols} ON tablets BEGIN "
            f"INSERT INTO tablets_fts(tablets_fts, rowid, {cols}) "
            f"VALUES ('delete', old.id, {old}); "
            f"INSERT INTO tablets_fts(rowid, {cols}) VALUES (new.id, {new}); END"
        )
        op.execute("INSERT INTO tablets_fts(tablets_fts) VALUES ('rebuild')")
    elif bind.dialect.name == "postgresql":
        document = " || ' ' || ".join(f"coalesce({c}, '')" for c in SEARCH_COLUMNS)
        op.execute(
            "ALTER TABLE tablets ADD COLUMN search_vector tsvector "
            f"GENERATED ALWAYS AS (to_tsvector('simple'::regconfig, {document})) STORED"
        )
        op.execute("CREATE INDEX ix_tablets_search_vector ON tablets USING GIN (search_vector)")


def _drop_search_structures() -> None:
    bind = op.get_bind()
    if bind.dialect.name == "sqlite":
        for trigger in ("tablets_fts_ai", "tablets_fts_ad", "tablets_fts_au"):
            op.execute(f"DROP TRIGGER IF EXISTS {trigger}")
        op.execute("DROP TABLE IF EXISTS tablets_fts")
    elif bind.dialect.name == "postgresql":
        op.execute("DROP INDEX IF EXISTS ix_tablets_search_vector")
        op.execute("ALTER TABLE tablets DROP COLUMN IF EXISTS search_vector")


def upgrade() -> None:
    op.create_table(
        "institutions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("name"),
    )
    op.create_table(
        "tablets",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("designation", sa.String(length=300), nullable=False),
        sa.Column("p_number", sa.String(length=32), nullable=True),
        sa.Column("museum_no", sa.String(length=300), nullable=True),
        sa.Column("collection", sa.String(length=300), nullable=True),
        sa.Column("owner", sa.String(length=300), nullable=True),
        sa.Column("excavation_no", sa.String(length=300), nullable=True),
        sa.Column("period", sa.String(length=200), nullable=True),
        sa.Column("provenience", sa.String(length=200), nullable=True),
        sa.Column("genre", sa.String(length=200), nullable=True),
        sa.Column("subgenre", sa.String(length=300), nullable=True),
        sa.Column("language", sa.String(length=200), nullable=True),
        sa.Column("material", sa.String(length=200), nullable=True),
        sa.Column("object_type", sa.String(length=200), nullable=True),
        sa.Column("height_mm", sa.Float(), nullable=True),
        sa.Column("width_mm", sa.Float(), nullable=True),
        sa.Column("thickness_mm", sa.Float(), nullable=True),
        sa.Column("primary_publication", sa.Text(), nullable=True),
        sa.Column("notes", sa.Text(), nullable=True),
        sa.Column("institution_id", sa.Integer(), nullable=True),
        sa.Column("is_public", sa.Boolean(), nullable=False),
        sa.Column("has_3d", sa.Boolean(), nullable=False),
        sa.Column("extra", sa.JSON(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["institution_id"], ["institutions.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("p_number"),
    )
    with op.batch_alter_table("tablets", schema=None) as batch_op:
        batch_op.create_index("ix_tablets_collection", ["collection"], unique=False)
        batch_op.create_index("ix_tablets_designation", ["designation"], unique=False)
        batch_op.create_index("ix_tablets_genre", ["genre"], unique=False)
        batch_op.create_index(batch_op.f("ix_tablets_has_3d"), ["has_3d"], unique=False)
        batch_op.create_index(
            batch_op.f("ix_tablets_institution_id"), ["institution_id"], unique=False
        )
        batch_op.create_index(batch_op.f("ix_tablets_is_public"), ["is_public"], unique=False)
        batch_op.create_index("ix_tablets_language", ["language"], unique=False)
        batch_op.create_index("ix_tablets_period", ["period"], unique=False)
        batch_op.create_index("ix_tablets_provenience", ["provenience"], unique=False)

    op.create_table(
        "users",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("email", sa.String(length=320), nullable=False),
        sa.Column("password_hash", sa.String(length=200), nullable=True),
        sa.Column(
            "role",
            sa.Enum(
                "admin",
                "staff",
                "reader",
                name="user_role",
                native_enum=False,
                create_constraint=True,
                length=16,
            ),
            nullable=False,
        ),
        sa.Column("institution_id", sa.Integer(), nullable=True),
        sa.Column("is_active", sa.Boolean(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["institution_id"], ["institutions.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("email"),
    )
    with op.batch_alter_table("users", schema=None) as batch_op:
        batch_op.create_index(
            batch_op.f("ix_users_institution_id"), ["institution_id"], unique=False
        )

    op.create_table(
        "api_tokens",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("token_hash", sa.String(length=64), nullable=False),
        sa.Column("prefix", sa.String(length=16), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("last_used_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("revoked_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("token_hash"),
    )
    with op.batch_alter_table("api_tokens", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_api_tokens_user_id"), ["user_id"], unique=False)

    op.create_table(
        "scans",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("tablet_id", sa.Integer(), nullable=False),
        sa.Column("face", sa.String(length=32), nullable=False),
        sa.Column("scan_uid", sa.String(length=100), nullable=True),
        sa.Column("bundle_key", sa.String(length=500), nullable=False),
        sa.Column("bundle_sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("manifest", sa.JSON(), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["tablet_id"], ["tablets.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("scan_uid"),
    )
    with op.batch_alter_table("scans", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_scans_tablet_id"), ["tablet_id"], unique=False)

    op.create_table(
        "uploads",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("tablet_id", sa.Integer(), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=True),
        sa.Column("filename", sa.String(length=500), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("ranges", sa.JSON(), nullable=False),
        sa.Column(
            "state",
            sa.Enum(
                "open",
                "complete",
                "failed",
                name="upload_state",
                native_enum=False,
                create_constraint=True,
                length=16,
            ),
            nullable=False,
        ),
        sa.Column("sha256", sa.String(length=64), nullable=True),
        sa.Column("storage_key", sa.String(length=500), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["tablet_id"], ["tablets.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
    )
    with op.batch_alter_table("uploads", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_uploads_tablet_id"), ["tablet_id"], unique=False)

    op.create_table(
        "jobs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("scan_id", sa.Integer(), nullable=True),
        sa.Column("tablet_id", sa.Integer(), nullable=False),
        sa.Column(
            "kind",
            sa.Enum(
                "reconstruct",
                "derive",
                "register",
                name="job_kind",
                native_enum=False,
                create_constraint=True,
                length=16,
            ),
            nullable=False,
        ),
        sa.Column(
            "state",
            sa.Enum(
                "queued",
                "running",
                "succeeded",
                "failed",
                name="job_state",
                native_enum=False,
                create_constraint=True,
                length=16,
            ),
            nullable=False,
        ),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("stage", sa.String(length=100), nullable=True),
        sa.Column("timings", sa.JSON(), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("enqueued_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("model_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["scan_id"], ["scans.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["tablet_id"], ["tablets.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_jobs_scan_id"), ["scan_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_jobs_state"), ["state"], unique=False)
        batch_op.create_index(batch_op.f("ix_jobs_tablet_id"), ["tablet_id"], unique=False)

    op.create_table(
        "models",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("scan_id", sa.Integer(), nullable=True),
        sa.Column("tablet_id", sa.Integer(), nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=False),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("storage_prefix", sa.String(length=500), nullable=False),
        sa.Column("report", sa.JSON(), nullable=False),
        sa.Column("assets", sa.JSON(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["job_id"], ["jobs.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["scan_id"], ["scans.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["tablet_id"], ["tablets.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("job_id"),
        sa.UniqueConstraint("scan_id", "version", name="uq_models_scan_version"),
    )
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_models_scan_id"), ["scan_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_models_tablet_id"), ["tablet_id"], unique=False)
    _create_search_structures()


def downgrade() -> None:
    _drop_search_structures()
    with op.batch_alter_table("models", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_models_tablet_id"))
        batch_op.drop_index(batch_op.f("ix_models_scan_id"))

    op.drop_table("models")
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_jobs_tablet_id"))
        batch_op.drop_index(batch_op.f("ix_jobs_state"))
        batch_op.drop_index(batch_op.f("ix_jobs_scan_id"))

    op.drop_table("jobs")
    with op.batch_alter_table("uploads", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_uploads_tablet_id"))

    op.drop_table("uploads")
    with op.batch_alter_table("scans", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_scans_tablet_id"))

    op.drop_table("scans")
    with op.batch_alter_table("api_tokens", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_api_tokens_user_id"))

    op.drop_table("api_tokens")
    with op.batch_alter_table("users", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_users_institution_id"))

    op.drop_table("users")
    with op.batch_alter_table("tablets", schema=None) as batch_op:
        batch_op.drop_index("ix_tablets_provenience")
        batch_op.drop_index("ix_tablets_period")
        batch_op.drop_index("ix_tablets_language")
        batch_op.drop_index(batch_op.f("ix_tablets_is_public"))
        batch_op.drop_index(batch_op.f("ix_tablets_institution_id"))
        batch_op.drop_index(batch_op.f("ix_tablets_has_3d"))
        batch_op.drop_index("ix_tablets_genre")
        batch_op.drop_index("ix_tablets_designation")
        batch_op.drop_index("ix_tablets_collection")

    op.drop_table("tablets")
    op.drop_table("institutions")
