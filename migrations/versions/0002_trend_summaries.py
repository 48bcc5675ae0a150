"""trend summaries: per-session-leg counts and per-metric included values

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "trend_session_legs",
        sa.Column("session_id", sa.String(length=32), nullable=False),
        sa.Column("leg", sa.String(length=5), nullable=False),
        sa.Column("patient_id", sa.String(length=32), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("n_strides", sa.Integer(), nullable=False),
        sa.Column("n_low_quality", sa.Integer(), nullable=False),
        sa.Column("n_fallback", sa.Integer(), nullable=False),
        sa.Column("n_gaps", sa.Integer(), nullable=False),
        sa.Column("walking_s", sa.Float(), nullable=False),
        sa.Column("algorithm_version", sa.String(length=32), nullable=True),
        sa.Column("refreshed_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["patient_id"], ["patients.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["session_id"], ["sessions.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("session_id", "leg"),
    )
    with op.batch_alter_table("trend_session_legs", schema=None) as batch_op:
        batch_op.create_index("ix_trend_session_legs_patient_time", ["patient_id", "started_at"], unique=False)

    op.create_table(
        "trend_metric_values",
        sa.Column("session_id", sa.String(length=32), nullable=False),
        sa.Column("leg", sa.String(length=5), nullable=False),
        sa.Column("metric", sa.String(length=40), nullable=False),
        sa.Column("patient_id", sa.String(length=32), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("n_included", sa.Integer(), nullable=False),
        sa.Column("n_implausible", sa.Integer(), nullable=False),
        sa.Column("mean", sa.Float(), nullable=True),
        sa.Column("sd", sa.Float(), nullable=True),
        sa.Column("median", sa.Float(), nullable=True),
        sa.Column("values", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["patient_id"], ["patients.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["session_id"], ["sessions.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("session_id", "leg", "metric"),
    )
    with op.batch_alter_table("trend_metric_values", schema=None) as batch_op:
        batch_op.create_index("ix_trend_metric_values_patient_metric_leg_time",
                              ["patient_id", "metric", "leg", "started_at"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("trend_metric_values", schema=None) as batch_op:
        batch_op.drop_index("ix_trend_metric_values_patient_metric_leg_time")
    op.drop_table("trend_metric_values")
    with op.batch_alter_table("trend_session_legs", schema=None) as batch_op:
        batch_op.drop_index("ix_trend_session_legs_patient_time")
    op.drop_table("trend_session_legs")
