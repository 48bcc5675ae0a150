"""trend quantiles: per-session p10/p90 so one-session buckets need no value arrays

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-22
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Nullable: rows written before this revision have none; the query then falls back to the value arrays.
    with op.batch_alter_table("trend_metric_values", schema=None) as batch_op:
        batch_op.add_column(sa.Column("p10", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("p90", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trend_metric_values", schema=None) as batch_op:
        batch_op.drop_column("p90")
        batch_op.drop_column("p10")
