"""licence and attribution of institutions (defaults), tablets and models (issue 18)

Revision ID: 0007_licences
Revises: 0006_session_version
Create Date: 2026-11-27 17:05:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007_licences"
down_revision: str | None = "0006_session_version"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TABLES = ("institutions", "tablets", "models")


def upgrade() -> None:
    for table in TABLES:
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.add_column(sa.Column("licence", sa.String(length=300), nullable=True))
            batch_op.add_column(sa.Column("attribution", sa.String(length=500), nullable=True))


def downgrade() -> None:
    for table in TABLES:
        with op.batch_alter_table(table, schema=None) as batch_op:
            batch_op.drop_column("attribution")
            batch_op.drop_column("licence")
