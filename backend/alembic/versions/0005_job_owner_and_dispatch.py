"""jobs.claimed_by, dispatch_failures, dispatch_after: dead attempts and broker outages

Jobs that older versions failed only because the broker was unreachable ("could not reach
the job queue") are queued again, awaiting dispatch: the sweeper sends them.

Revision ID: 0005_job_dispatch
Revises: 0004_search
Create Date: 2026-11-27 16:30:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005_job_dispatch"
down_revision: str | None = "0004_search"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("claimed_by", sa.String(length=200), nullable=True))
        batch_op.add_column(
            sa.Column("dispatch_failures", sa.Integer(), server_default="0", nullable=False)
        )
        batch_op.add_column(sa.Column("dispatch_after", sa.DateTime(timezone=True), nullable=True))
        batch_op.create_index("ix_jobs_dispatch_after", ["dispatch_after"], unique=False)
    op.execute(
        "UPDATE jobs SET state = 'queued', error = NULL, stage = 'awaiting dispatch', "
        "finished_at = NULL, enqueued_at = NULL, dispatch_failures = 1, "
        "dispatch_after = CURRENT_TIMESTAMP "
        "WHERE state = 'failed' AND error LIKE 'could not reach the job queue%'"
    )


def downgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index("ix_jobs_dispatch_after")
        batch_op.drop_column("dispatch_after")
        batch_op.drop_column("dispatch_failures")
        batch_op.drop_column("claimed_by")
