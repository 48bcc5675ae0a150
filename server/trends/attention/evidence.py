"""Keep each patient's precomputed attention evidence in step with their sessions (called when one is processed)."""

from __future__ import annotations

from sqlalchemy import delete, exists, select
from sqlalchemy.orm import Session as DbSession

from server.enums import SessionStatus
from server.sessions.models import Session
from server.trends.attention.service import evidence_document
from server.trends.models import AttentionEvidence
from server.utc import utcnow


def refresh_patient(db: DbSession, patient_id: str) -> None:
    """Recompute the patient's evidence row from their summaries (deleted when no session is processed).
    Flushes; the caller commits."""
    db.flush()
    found = evidence_document(db, patient_id)
    row = db.get(AttentionEvidence, patient_id)
    if found is None:
        if row is not None:
            db.execute(delete(AttentionEvidence).where(AttentionEvidence.patient_id == patient_id))
        db.flush()
        return
    as_of, doc = found
    if row is None:
        db.add(AttentionEvidence(patient_id=patient_id, as_of=as_of, flags=doc, refreshed_at=utcnow()))
    else:
        row.as_of, row.flags, row.refreshed_at = as_of, doc, utcnow()
    db.flush()


def patients_without_evidence(db: DbSession) -> list[str]:
    """Patients with a processed session but no evidence row."""
    return list(db.execute(
        select(Session.patient_id).distinct()
        .where(Session.status.in_([SessionStatus.done, SessionStatus.failed]),
               ~exists().where(AttentionEvidence.patient_id == Session.patient_id))
    ).scalars())
