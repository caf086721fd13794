"""ids never reused on SQLite: AUTOINCREMENT on every table whose integer ids name URLs

SQLite's plain ``INTEGER PRIMARY KEY`` hands out max(id) + 1, so deleting the newest record
gave its id, and so its stable URL (``/tablets/7526``), to the next one. ``AUTOINCREMENT``
keeps the highest id ever used (``sqlite_sequence``) and never goes below it. Each table is
rebuilt in batch mode (SQLite cannot change a primary key in place); the copied rows keep
their ids, which also seeds ``sqlite_sequence`` with the highest one present (an id deleted
before this migration is not known and may still come back once). Indexes and triggers
(the full-text triggers on ``tablets``) are taken from the old table's own SQL and made
again as they were. (Uploads have uuid ids.) PostgreSQL: nothing to do, its sequences never hand an id out twice.

Revision ID: 0009_sqlite_autoincrement
Revises: 0008_annotations
Create Date: 2026-11-28 01:40:00
"""

from collections.abc import Sequence

from alembic import op
from sqlalchemy import text

revision: str = "0009_sqlite_autoincrement"
down_revision: str | None = "0008_annotations"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Parents before children (foreign keys are off during migrations: backend/alembic/env.py).
TABLES = (
    "institutions",
    "users",
    "api_tokens",
    "tablets",
    "scans",
    "jobs",
    "models",
    "annotations",
)


def _rebuild(table: str, *, autoincrement: bool) -> None:
    bind = op.get_bind()
    # Indexes and triggers exactly as they are (batch mode drops the triggers, and would
    # reflect partial indexes only as well as SQLAlchemy's reflection knows them).
    kept = bind.execute(
        text(
            "SELECT type, name, sql FROM sqlite_master "
            "WHERE tbl_name = :table AND type IN ('index', 'trigger') AND sql IS NOT NULL"
        ),
        {"table": table},
    ).all()
    with op.batch_alter_table(
        table, recreate="always", table_kwargs={"sqlite_autoincrement": autoincrement}
    ):
        pass
    for kind, name, sql in kept:
        op.execute(f'DROP {kind.upper()} IF EXISTS "{name}"')
        op.execute(sql)


def upgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    for table in TABLES:
        _rebuild(table, autoincrement=True)


def downgrade() -> None:
    if op.get_bind().dialect.name != "sqlite":
        return
    for table in reversed(TABLES):
        _rebuild(table, autoincrement=False)
