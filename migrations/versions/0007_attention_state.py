"""attention state: exposure counters and the rules version on each patient's attention row

``attention_evidence`` (one row per patient with a processed session, refreshed in the transaction that stores a
session's results) gains the patient's exposure, the number of processed sessions and the first one's start, and
``rules_version``, the version of the flag rules its flags were computed with. The counters are backfilled here
from ``sessions``; ``rules_version`` stays NULL, so ``gaitmon migrate`` recomputes every row's flags right after
(``server.trends.summaries.backfill``: every patient whose row is missing or from other rules).

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-01
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_PROCESSED = "sessions.patient_id = attention_evidence.patient_id AND sessions.status IN ('done', 'failed')"


def upgrade() -> None:
    with op.batch_alter_table("attention_evidence", schema=None) as batch_op:
        batch_op.add_column(sa.Column("n_sessions", sa.Integer(), server_default="0", nullable=False))
        batch_op.add_column(sa.Column("first_session_at", sa.DateTime(timezone=True), nullable=True))
        batch_op.add_column(sa.Column("rules_version", sa.String(length=16), nullable=True))
    op.execute(f"UPDATE attention_evidence SET n_sessions = (SELECT count(*) FROM sessions WHERE {_PROCESSED}), "
               f"first_session_at = (SELECT min(sessions.started_at) FROM sessions WHERE {_PROCESSED})")


def downgrade() -> None:
    with op.batch_alter_table("attention_evidence", schema=None) as batch_op:
        batch_op.drop_column("rules_version")
        batch_op.drop_column("first_session_at")
        batch_op.drop_column("n_sessions")
