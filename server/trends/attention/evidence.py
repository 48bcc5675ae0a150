"""Keep each patient's precomputed attention evidence in step with their sessions (called when one is processed)."""

from __future__ import annotations

import json

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
    index = ";".join(f"{preset}|{leg}|{f['kind']}|{f['severity']}|{f.get('effect') or 0.0}"
                     for preset, per in doc["presets"].items()
                     for leg, f in [*per["legs"].items(), ("*", per["sensor"])] if f)
    fields = {"as_of": as_of, "legs": ",".join(doc["legs"]), "flag_index": index,
              "flags": json.dumps(doc["presets"], allow_nan=False), "refreshed_at": utcnow()}
    if row is None:
        db.add(AttentionEvidence(patient_id=patient_id, **fields))
    else:
        for k, v in fields.items():
            setattr(row, k, v)
    db.flush()


def patients_without_evidence(db: DbSession) -> list[str]:
    """Patients with a processed session but no evidence row."""
    return list(db.execute(
        select(Session.patient_id).distinct()
        .where(Session.status.in_([SessionStatus.done, SessionStatus.failed]),
               ~exists().where(AttentionEvidence.patient_id == Session.patient_id))
    ).scalars())
