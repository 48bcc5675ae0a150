"""stride activity and fallback; trend summaries per session, leg and activity

Strides say which activity they were processed as and whether they are a fallback of that activity's primary
estimator. Existing strides are backfilled from their session: a ``running`` session's strides are running (and
no fallback: ``ekf`` is the running path's primary estimator), every other stride is walking, a fallback when its
angle came from the complementary filter (``cf``), the walking fallback of the processing run that wrote it.

The trend summary tables gain ``activity`` in their primary key. They hold only values derived from the strides,
so they are recreated empty here and ``gaitmon migrate`` refills them from the backfilled strides right after
(``server.trends.summaries.backfill``: every processed session without a summary).

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _trend_tables(with_activity: bool) -> None:
    activity = [sa.Column("activity", sa.String(length=16), nullable=False)] if with_activity else []
    key = ["activity"] if with_activity else []
    op.create_table(
        "trend_session_legs",
        sa.Column("session_id", sa.String(length=32), nullable=False),
        sa.Column("leg", sa.String(length=5), nullable=False),
        *activity,
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
        sa.PrimaryKeyConstraint("session_id", "leg", *key),
    )
    op.create_index("ix_trend_session_legs_patient_time", "trend_session_legs",
                    ["patient_id", *key, "started_at"], unique=False)
    op.create_table(
        "trend_metric_values",
        sa.Column("session_id", sa.String(length=32), nullable=False),
        sa.Column("leg", sa.String(length=5), nullable=False),
        *[sa.Column("activity", sa.String(length=16), nullable=False) for _ in key],
        sa.Column("metric", sa.String(length=40), nullable=False),
        sa.Column("patient_id", sa.String(length=32), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("n_included", sa.Integer(), nullable=False),
        sa.Column("n_implausible", sa.Integer(), nullable=False),
        sa.Column("mean", sa.Float(), nullable=True),
        sa.Column("sd", sa.Float(), nullable=True),
        sa.Column("median", sa.Float(), nullable=True),
        sa.Column("values", sa.LargeBinary(), nullable=False),
        sa.Column("p10", sa.Float(), nullable=True),
        sa.Column("p90", sa.Float(), nullable=True),
        sa.ForeignKeyConstraint(["patient_id"], ["patients.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["session_id"], ["sessions.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("session_id", "leg", *key, "metric"),
    )
    op.create_index("ix_trend_metric_values_patient_metric_leg_time", "trend_metric_values",
                    ["patient_id", "metric", "leg", *key, "started_at"], unique=False)


def _drop_trend_tables() -> None:
    op.drop_index("ix_trend_metric_values_patient_metric_leg_time", table_name="trend_metric_values")
    op.drop_table("trend_metric_values")
    op.drop_index("ix_trend_session_legs_patient_time", table_name="trend_session_legs")
    op.drop_table("trend_session_legs")


def upgrade() -> None:
    with op.batch_alter_table("strides", schema=None) as batch_op:
        batch_op.add_column(sa.Column("activity", sa.String(length=16), nullable=False,
                                      server_default="walking"))
        batch_op.add_column(sa.Column("fallback", sa.Boolean(), nullable=False, server_default=sa.false()))
    op.execute(
        "UPDATE strides SET activity = 'running' "
        "WHERE session_id IN (SELECT id FROM sessions WHERE activity = 'running')")
    op.execute("UPDATE strides SET fallback = (estimator = 'cf') WHERE activity = 'walking'")
    # The defaults served the backfill only: every stride written from now on says both itself.
    with op.batch_alter_table("strides", schema=None) as batch_op:
        batch_op.alter_column("activity", server_default=None)
        batch_op.alter_column("fallback", server_default=None)
    _drop_trend_tables()
    _trend_tables(with_activity=True)


def downgrade() -> None:
    _drop_trend_tables()
    _trend_tables(with_activity=False)
    with op.batch_alter_table("strides", schema=None) as batch_op:
        batch_op.drop_column("fallback")
        batch_op.drop_column("activity")
