"""Deleting a patient with everything that names them."""

from __future__ import annotations

from sqlalchemy import delete, select
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Token
from server.patients.models import Patient
from server.processing.queue import forget_sessions
from server.results.models import KneeAngleTrace, Stride
from server.sessions.models import Batch, Session, SessionSensor


def delete_patient(db: DbSession, patient_id: str) -> None:
    """Delete the patient, their sessions (raw batches, results), tokens and the job queue's rows of those
    sessions, in the caller's transaction (the caller commits)."""
    session_ids = list(db.scalars(select(Session.id).where(Session.patient_id == patient_id)))
    forget_sessions(db, session_ids)
    in_sessions = select(Session.id).where(Session.patient_id == patient_id).scalar_subquery()
    # Explicit deletes of the core tables (children first) so nothing depends on the database enforcing
    # ON DELETE CASCADE; tables of other modules reference sessions/patients with ON DELETE CASCADE.
    for model in (Batch, Stride, KneeAngleTrace, SessionSensor):
        db.execute(delete(model).where(model.session_id.in_(in_sessions)))
    db.execute(delete(Session).where(Session.patient_id == patient_id))
    db.execute(delete(Token).where(Token.patient_id == patient_id))
    db.execute(delete(Patient).where(Patient.id == patient_id))
