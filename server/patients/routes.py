"""Patients: create, list (keyset pages), read, delete with all their data, device tokens, their sessions."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Query, Response
from sqlalchemy import and_, or_, select

from server.auth.models import Clinician, Token
from server.auth.routes import token_out
from server.auth.schemas import DeviceTokenCreated, DeviceTokenIn, TokenOut
from server.auth.service import get_patient_for, issue_token, require_role
from server.deps import Caller, Db
from server.enums import Role
from server.errors import invalid
from server.pagination import after_cursor, decode_cursor, encode_cursor
from server.patients import service as patient_service
from server.patients.models import Patient
from server.patients.schemas import PatientIn, PatientOut, PatientPage, PatientPatch
from server.schema_types import SafeStr
from server.sessions.models import Session
from server.sessions.schemas import SessionListItem, SessionPage

log = logging.getLogger("gaitmon.api")
router = APIRouter(prefix="/v1/patients", tags=["patients"])


def patient_out(p: Patient) -> PatientOut:
    """The response form of a patient."""
    return PatientOut.model_validate(p)


@router.post("", status_code=201, response_model=PatientOut,
             responses={403: {"description": "Device tokens may not create patients"}},
             summary="Create a patient owned by the calling clinician (an admin may name the clinician)")
def create_patient(body: PatientIn, db: Db, caller: Caller) -> PatientOut:
    """Create a patient owned by the calling clinician (an admin may name the clinician)."""
    require_role(caller, Role.admin, Role.clinician, action="create patients")
    if caller.role == Role.clinician:
        if body.clinician_id is not None and body.clinician_id != caller.clinician_id:
            raise invalid("clinician_id", "a clinician creates patients for themself only")
        owner = caller.clinician_id
    else:
        owner = body.clinician_id
        if owner is not None and db.get(Clinician, owner) is None:
            raise invalid("clinician_id", "no such clinician")
    patient = Patient(clinician_id=owner, external_id=body.external_id, display_name=body.display_name,
                      affected_leg=body.affected_leg, timezone=body.timezone,
                      prescribed_sessions_per_week=body.prescribed_sessions_per_week)
    db.add(patient)
    db.commit()
    log.info("patient %s created by token %s", patient.id, caller.token_id)
    return patient_out(patient)


@router.get("", response_model=PatientPage, summary="The caller's patients (admin: all), oldest first",
            responses={400: {"description": "cursor is not a next_cursor of this API"},
                       403: {"description": "Device tokens may not list patients"}})
def list_patients(db: Db, caller: Caller, limit: int = Query(50, ge=1, le=200),
                  cursor: str | None = Query(None, description="next_cursor of the previous page"),
                  search: SafeStr = Query("", max_length=100,
                                                description="Only patients whose external_id contains this text "
                                                            "(case-insensitive)")) -> PatientPage:
    """The caller's patients, one page at a time."""
    require_role(caller, Role.admin, Role.clinician, action="list patients")
    stmt = patient_service.patients_of(caller, search)
    if cursor:
        stmt = stmt.where(after_cursor(Patient.created_at, Patient.id, cursor))
    rows = db.scalars(stmt.order_by(*patient_service.PATIENT_ORDER).limit(limit + 1)).all()
    page = rows[:limit]
    next_cursor = encode_cursor(page[-1].created_at, page[-1].id) if len(rows) > limit else None
    return PatientPage(items=[patient_out(p) for p in page], next_cursor=next_cursor)


@router.get("/{patient_id}", response_model=PatientOut, summary="One patient")
def get_patient(patient_id: str, db: Db, caller: Caller) -> PatientOut:
    """One patient the caller may see."""
    return patient_out(get_patient_for(db, caller, patient_id))


@router.patch("/{patient_id}", response_model=PatientOut, summary="Change a patient's details",
              operation_id="updatePatient", responses={403: {"description": "Device tokens may not change patients"}})
def patch_patient(patient_id: str, body: PatientPatch, db: Db, caller: Caller) -> PatientOut:
    """Change some fields of a patient."""
    require_role(caller, Role.admin, Role.clinician, action="change patients")
    patient = get_patient_for(db, caller, patient_id)
    for field, value in body.model_dump(exclude_unset=True).items():
        setattr(patient, field, value)
    db.commit()
    return patient_out(patient)


@router.delete("/{patient_id}", status_code=204, response_class=Response,
               responses={403: {"description": "Device tokens may not delete patients"}},
               summary="Delete the patient and all its data (sessions, raw batches, results, tokens)")
def delete_patient(patient_id: str, db: Db, caller: Caller) -> Response:
    """Delete a patient with every session, result and token."""
    require_role(caller, Role.admin, Role.clinician, action="delete patients")
    patient = get_patient_for(db, caller, patient_id)
    patient_service.delete_patient(db, patient.id)
    db.commit()
    log.info("patient %s and all its data deleted by token %s", patient_id, caller.token_id)
    return Response(status_code=204)


@router.post("/{patient_id}/device-tokens", status_code=201, response_model=DeviceTokenCreated,
             responses={403: {"description": "Device tokens may not create device tokens"}},
             summary="Enrol a device: a token bound to this patient (shown once)")
def create_device_token(patient_id: str, db: Db, caller: Caller,
                        body: DeviceTokenIn | None = None) -> DeviceTokenCreated:
    """Issue a device token for the patient's app (shown once)."""
    require_role(caller, Role.admin, Role.clinician, action="create device tokens")
    patient = get_patient_for(db, caller, patient_id)
    name = body.name if body else None
    token, plaintext = issue_token(db, role=Role.device, name=name, patient_id=patient.id)
    db.commit()
    log.info("device token %s for patient %s created by token %s", token.id, patient.id, caller.token_id)
    return DeviceTokenCreated(token=plaintext, token_id=token.id, patient_id=patient.id, name=name)


@router.get("/{patient_id}/device-tokens", response_model=list[TokenOut],
            responses={403: {"description": "Device tokens may not list device tokens"}},
            summary="The patient's device tokens (without their secret)")
def list_device_tokens(patient_id: str, db: Db, caller: Caller) -> list[TokenOut]:
    """The device tokens of a patient (metadata only)."""
    require_role(caller, Role.admin, Role.clinician, action="list device tokens")
    patient = get_patient_for(db, caller, patient_id)
    rows = db.scalars(select(Token).where(Token.patient_id == patient.id, Token.role == Role.device)
                      .order_by(Token.created_at, Token.id)).all()
    return [token_out(t) for t in rows]


@router.get("/{patient_id}/sessions", response_model=SessionPage, operation_id="listPatientSessions",
            responses={400: {"description": "cursor is not a next_cursor of this API"}},
            summary="The patient's sessions, newest first")
def list_sessions(patient_id: str, db: Db, caller: Caller, limit: int = Query(50, ge=1, le=200),
                  cursor: str | None = Query(None, description="next_cursor of the previous page")) -> SessionPage:
    """A patient's sessions, newest first, one page at a time."""
    patient = get_patient_for(db, caller, patient_id)
    stmt = patient_service.sessions_of(patient.id)
    if cursor:
        # Newest first: "after" the cursor means older, so the keyset condition is mirrored.
        started, sid = decode_cursor(cursor)
        stmt = stmt.where(or_(Session.started_at < started, and_(Session.started_at == started, Session.id < sid)))
    rows = db.scalars(stmt.order_by(*patient_service.SESSION_ORDER).limit(limit + 1)).all()
    page = rows[:limit]
    next_cursor = encode_cursor(page[-1].started_at, page[-1].id) if len(rows) > limit else None
    items = [SessionListItem.model_validate(s) for s in page]
    return SessionPage(items=items, next_cursor=next_cursor)
