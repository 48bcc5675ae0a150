"""Keep each patient's attention row (precomputed flags and exposure) in step with their sessions.

:func:`refresh_patient` runs in the transaction that stores a session's results (done or failed, first run or
reprocess, via :func:`server.trends.summaries.refresh_session`); deleting a patient deletes the row (ON DELETE
CASCADE). :func:`patients_needing_evidence` lists rows to recompute after a rule change (``RULES_VERSION``).
"""

from __future__ import annotations

import json

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session as DbSession

from server.enums import SessionStatus
from server.sessions.models import Session
from server.trends.attention.service import evidence_document
from server.trends.models import AttentionEvidence
from server.utc import utcnow

# Bump whenever a rule or a preset changes what a stored flag would say: backfill recomputes older rows.
RULES_VERSION = "2026-12-01c"

_PROCESSED = (SessionStatus.done, SessionStatus.failed)


def refresh_patient(db: DbSession, patient_id: str) -> None:
    """Recompute the patient's attention row from their summaries (deleted when no session is processed).
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
    n_sessions, first = db.execute(select(func.count(), func.min(Session.started_at)).where(
        Session.patient_id == patient_id, Session.status.in_(_PROCESSED))).one()
    index = ";".join(f"{preset}|{leg}|{f['kind']}|{f['severity']}|{f.get('effect') or 0.0}"
                     for preset, per in doc["presets"].items()
                     for leg, f in [*per["legs"].items(), ("*", per["sensor"])] if f)
    fields = {"as_of": as_of, "legs": ",".join(doc["legs"]), "flag_index": index,
              "flags": json.dumps(doc["presets"], allow_nan=False), "n_sessions": int(n_sessions),
              "first_session_at": first, "rules_version": RULES_VERSION, "refreshed_at": utcnow()}
    if row is None:
        db.add(AttentionEvidence(patient_id=patient_id, **fields))
    else:
        for k, v in fields.items():
            setattr(row, k, v)
    db.flush()


def patients_needing_evidence(db: DbSession) -> list[str]:
    """Patients with a processed session whose attention row is missing or was computed by other rules."""
    current = (select(AttentionEvidence.patient_id)
               .where(AttentionEvidence.rules_version == RULES_VERSION).scalar_subquery())
    return list(db.execute(
        select(Session.patient_id).distinct()
        .where(Session.status.in_(_PROCESSED), Session.patient_id.not_in(current))
    ).scalars())
