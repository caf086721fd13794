"""tablets.p_number unique per institution, not across the library (issue 16, item 7)

A P-number was unique library-wide, so an institution could block another from registering
its own record of a tablet, and the 409 revealed private records. Now the same P-number may
exist once per institution, and once among records of no institution (catalogue records
kept by admins). ``ix_tablets_p_number`` serves look-ups by P-number across institutions.

The SQLite table is rebuilt (batch mode) to drop its unnamed UNIQUE; the rebuild drops the
full-text triggers of 0001, which are created again. Downgrade fails while two records
share a P-number.

Revision ID: 0003_p_number
Revises: 0002
Create Date: 2026-11-27 16:10:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003_p_number"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# The same list as 0001 (its triggers are what the rebuild removes).
SEARCH_COLUMNS = (
    "designation",
    "p_number",
    "museum_no",
    "excavation_no",
    "primary_publication",
    "notes",
)
NO_INSTITUTION = sa.text("institution_id IS NULL")


def _create_fts_triggers() -> None:
    cols = ", ".join(SEARCH_COLUMNS)
    new = ", ".join(f"new.{c}" for c in SEARCH_COLUMNS)
    old = ", ".join(f"old.{c}" for c in SEARCH_COLUMNS)
    op.execute(
        "CREATE TRIGGER IF NOT EXISTS tablets_fts_ai AFTER INSERT ON tablets BEGIN "
        f"INSERT INTO tablets_fts(rowid, {cols}) VALUES (new.id, {new}); END"
    )
    op.execute(
        "CREATE TRIGGER IF NOT EXISTS tablets_fts_ad AFTER DELETE ON tablets BEGIN "
        f"INSERT INTO tablets_fts(tablets_fts, rowid, {cols}) "
        f"VALUES ('delete', old.id, {old}); END"
    )
    op.execute(
        f"CREATE TRIGGER IF NOT EXISTS tablets_fts_au AFTER UPDATE OF {cols} ON tablets BEGIN "
        f"INSERT INTO tablets_fts(tablets_fts, rowid, {cols}) "
        f"VALUES ('delete', old.id, {old}); "
        f"INSERT INTO tablets_fts(rowid, {cols}) VALUES (new.id, {new}); END"
    )


def upgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        # The UNIQUE of 0001 has no name in SQLite: name it by convention to drop it.
        with op.batch_alter_table(
            "tablets",
            recreate="always",
            naming_convention={"uq": "uq_%(table_name)s_%(column_0_name)s"},
        ) as batch_op:
            batch_op.drop_constraint("uq_tablets_p_number", type_="unique")
        _create_fts_triggers()
    else:
        op.drop_constraint("tablets_p_number_key", "tablets", type_="unique")
    op.create_index("ix_tablets_p_number", "tablets", ["p_number"])
    op.create_index(
        "uq_tablets_institution_p_number", "tablets", ["institution_id", "p_number"], unique=True
    )
    op.create_index(
        "uq_tablets_p_number_no_institution",
        "tablets",
        ["p_number"],
        unique=True,
        sqlite_where=NO_INSTITUTION,
        postgresql_where=NO_INSTITUTION,
    )


def downgrade() -> None:
    op.drop_index("uq_tablets_p_number_no_institution", table_name="tablets")
    op.drop_index("uq_tablets_institution_p_number", table_name="tablets")
    op.drop_index("ix_tablets_p_number", table_name="tablets")
    if op.get_bind().dialect.name == "sqlite":
        with op.batch_alter_table("tablets", recreate="always") as batch_op:
            batch_op.create_unique_constraint("uq_tablets_p_number", ["p_number"])
        _create_fts_triggers()
    else:
        op.create_unique_constraint("tablets_p_number_key", "tablets", ["p_number"])
