"""Patients: who may see which (list queries shared by the API and the pages), and deleting a patient with
everything that names them."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import Select, delete, func, select
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Token
from server.auth.service import Principal
from server.enums import Role, SessionStatus
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


# The list orders of the API's keyset pages and the clinician pages' numbered ones (the keyset cursors encode
# these columns): patients oldest first, a patient's sessions newest first.
PATIENT_ORDER = (Patient.created_at, Patient.id)
SESSION_ORDER = (Session.started_at.desc(), Session.id.desc())


def count(db: DbSession, stmt: Select) -> int:
    """How many rows ``stmt`` selects."""
    return int(db.scalar(select(func.count()).select_from(stmt.order_by(None).subquery())) or 0)


@dataclass(frozen=True)
class NumberedPage:
    """One numbered page of a list (patients or sessions) with the list's total."""

    items: list
    total: int
    offset: int
    limit: int


def patient_page(db: DbSession, principal: Principal, *, search: str = "", offset: int = 0,
                 limit: int = 25) -> NumberedPage:
    """The principal's patients (:func:`patients_of`) in :data:`PATIENT_ORDER`, ``limit`` from ``offset``."""
    stmt = patients_of(principal, search)
    rows = db.scalars(stmt.order_by(*PATIENT_ORDER).offset(offset).limit(limit)).all()
    return NumberedPage(list(rows), count(db, stmt), offset, limit)


def session_page(db: DbSession, patient_id: str, *, offset: int = 0, limit: int = 20) -> NumberedPage:
    """The patient's sessions (:func:`sessions_of`) in :data:`SESSION_ORDER`, ``limit`` from ``offset``."""
    stmt = sessions_of(patient_id)
    rows = db.scalars(stmt.order_by(*SESSION_ORDER).offset(offset).limit(limit)).all()
    return NumberedPage(list(rows), count(db, stmt), offset, limit)


def first_done_session(db: DbSession, patient_id: str) -> Session | None:
    """The patient's earliest processed session (the reference of the session page's gait-cycle plot and the
    start of the patient page's time axis)."""
    return db.scalar(sessions_of(patient_id).where(Session.status == SessionStatus.done)
                     .order_by(Session.started_at, Session.id).limit(1))


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
