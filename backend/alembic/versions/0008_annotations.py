"""annotations (W3C Web Annotations on model versions) and the tablets' ATF text (issue 20)

Revision ID: 0008_annotations
Revises: 0007_licences
Create Date: 2026-11-27 21:15:00
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008_annotations"
down_revision: str | None = "0007_licences"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("tablets", schema=None) as batch_op:
        batch_op.add_column(sa.Column("atf", sa.Text(), nullable=True))
    op.create_table(
        "annotations",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "model_id", sa.Integer(), sa.ForeignKey("models.id", ondelete="CASCADE"), nullable=False
        ),
        sa.Column(
            "tablet_id",
            sa.Integer(),
            sa.ForeignKey("tablets.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column(
            "creator_id",
            sa.Integer(),
            sa.ForeignKey("users.id", ondelete="SET NULL"),
            nullable=True,
        ),
        sa.Column("reference", sa.String(length=40), nullable=False),
        sa.Column("reading", sa.String(length=200), nullable=True),
        sa.Column("comment", sa.Text(), nullable=True),
        sa.Column("polygon_mm", sa.JSON(), nullable=False),
        sa.Column("polygon_px", sa.JSON(), nullable=True),
        sa.Column("image_face", sa.String(length=32), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_index("ix_annotations_model_id", "annotations", ["model_id"])
    op.create_index("ix_annotations_tablet_id", "annotations", ["tablet_id"])


def downgrade() -> None:
    op.drop_index("ix_annotations_tablet_id", table_name="annotations")
    op.drop_index("ix_annotations_model_id", table_name="annotations")
    op.drop_table("annotations")
    with op.batch_alter_table("tablets", schema=None) as batch_op:
        batch_op.drop_column("atf")
