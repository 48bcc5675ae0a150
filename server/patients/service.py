"""Patients: who may see which (list queries shared by the API and the pages), and deleting a patient with
everything that names them."""

from __future__ import annotations

from sqlalchemy import Select, delete, func, select
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Token
from server.auth.service import Principal
from server.enums import Role
from server.patients.models import Patient
from server.processing.queue import forget_sessions
from server.results.models import KneeAngleTrace, Stride
from server.sessions.models import Batch, Session, SessionSensor


def patients_of(principal: Principal, search: str = "") -> Select:
    """The principal's patients (admin: all), optionally those whose external id contains ``search``
    (case-insensitive, taken literally: ``%`` and ``_`` match themselves); unordered."""
    stmt = select(Patient)
    if principal.role == Role.clinician:
        stmt = stmt.where(Patient.clinician_id == principal.clinician_id)
    if search:
        escaped = search.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        stmt = stmt.where(func.lower(Patient.external_id).like(f"%{escaped.lower()}%", escape="\\"))
    return stmt


def sessions_of(patient_id: str) -> Select:
    """The patient's sessions; unordered."""
    return select(Session).where(Session.patient_id == patient_id)


def count(db: DbSession, stmt: Select) -> int:
    """How many rows ``stmt`` selects."""
    return int(db.scalar(select(func.count()).select_from(stmt.order_by(None).subquery())) or 0)


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
