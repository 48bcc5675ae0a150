"""knee calibrations: a patient's measured standing knee flexion per leg, valid from when it was measured

A new table only; existing sessions are not touched (their summaries say the level was assumed until they are
reprocessed).

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "knee_calibrations",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("patient_id", sa.String(length=32), nullable=False),
        sa.Column("leg", sa.String(length=5), nullable=False),
        sa.Column("standing_knee_deg", sa.Float(), nullable=False),
        sa.Column("measured_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("method", sa.String(length=16), nullable=False),
        sa.Column("note", sa.Text(), nullable=True),
        sa.Column("recorded_by_token_id", sa.String(length=32), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["patient_id"], ["patients.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_knee_calibrations_patient_leg_time", "knee_calibrations",
                    ["patient_id", "leg", "measured_at"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_knee_calibrations_patient_leg_time", table_name="knee_calibrations")
    op.drop_table("knee_calibrations")
