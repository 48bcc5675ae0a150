"""attention evidence: per session-leg implausible, expected strides and sensor coverage; prescribed schedule

``trend_session_legs`` gains what the attention list's ``sensor_trouble`` judges: quality-passing strides with an
implausible knee angle, the strides the leg should have given and the share of the session its sensors covered.
They derive from strides and raw batches only, so the summaries are emptied here and ``gaitmon migrate`` refills
them right after (``server.trends.summaries.backfill``: every processed session without a summary).
``patients.prescribed_sessions_per_week`` (optional) is the schedule the ``silent`` flag follows.
``attention_evidence`` holds each patient's flags as of their latest processed session (refilled by the same
backfill), so the attention list reads one small row per patient.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.execute("DELETE FROM trend_metric_values")
    op.execute("DELETE FROM trend_session_legs")
    with op.batch_alter_table("trend_session_legs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("n_implausible", sa.Integer(), server_default="0", nullable=False))
        batch_op.add_column(sa.Column("n_expected", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("coverage", sa.Float(), nullable=True))
    with op.batch_alter_table("patients", schema=None) as batch_op:
        batch_op.add_column(sa.Column("prescribed_sessions_per_week", sa.Float(), nullable=True))
    op.create_table(
        "attention_evidence",
        sa.Column("patient_id", sa.String(length=32), nullable=False),
        sa.Column("as_of", sa.DateTime(timezone=True), nullable=False),
        sa.Column("legs", sa.String(length=32), nullable=False),
        sa.Column("flag_index", sa.Text(), nullable=False),
        sa.Column("flags", sa.Text(), nullable=False),
        sa.Column("refreshed_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["patient_id"], ["patients.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("patient_id"),
    )


def downgrade() -> None:
    op.drop_table("attention_evidence")
    with op.batch_alter_table("patients", schema=None) as batch_op:
        batch_op.drop_column("prescribed_sessions_per_week")
    with op.batch_alter_table("trend_session_legs", schema=None) as batch_op:
        batch_op.drop_column("coverage")
        batch_op.drop_column("n_expected")
        batch_op.drop_column("n_implausible")
