"""Knee calibrations of a patient: record, list (newest measurement first), delete.

Clinicians (of the patient) and admins write; the patient's device token may read them; anyone else gets 404
like every other patient route. Nothing is reprocessed here: the answer counts the processed sessions a
reprocess would now give another calibration (:mod:`server.calibrations.service`).
"""

from __future__ import annotations

import logging

from fastapi import APIRouter, Query, Response
from sqlalchemy import and_, or_

from server.auth.service import get_patient_for, require_role
from server.calibrations.models import KneeCalibration
from server.calibrations.schemas import (
    MAX_AFFECTED_IDS,
    CalibrationCreated,
    CalibrationIn,
    CalibrationOut,
    CalibrationPage,
)
from server.calibrations.service import affected_sessions, calibrations_of, record
from server.db import storable_key
from server.deps import Caller, Db
from server.enums import Leg, Role
from server.errors import not_found
from server.pagination import decode_cursor, encode_cursor

log = logging.getLogger("gaitmon.api")
router = APIRouter(prefix="/v1/patients/{patient_id}/calibrations", tags=["patients"])

# Response header of DELETE (204 has no body): how many processed sessions a reprocess would now change.
AFFECTED_HEADER = "Gaitmon-Affected-Sessions"


@router.post("", status_code=201, response_model=CalibrationCreated,
             responses={403: {"description": "Device tokens may not record calibrations"}},
             summary="Record a measured standing knee flexion of one leg (clinician/admin)")
def create_calibration(patient_id: str, body: CalibrationIn, db: Db, caller: Caller) -> CalibrationCreated:
    """Record a calibration; sessions already processed keep their results until they are reprocessed."""
    require_role(caller, Role.admin, Role.clinician, action="record calibrations")
    patient = get_patient_for(db, caller, patient_id)
    cal, affected = record(db, patient.id, body, caller.token_id)
    db.commit()
    log.info("calibration %s (%s leg, %.1f deg) for patient %s recorded by token %s; %d session(s) affected",
             cal.id, cal.leg, cal.standing_knee_deg, patient.id, caller.token_id, len(affected))
    return CalibrationCreated.model_validate({**CalibrationOut.model_validate(cal).model_dump(),
                                              "affected_sessions": len(affected),
                                              "affected_session_ids": affected[:MAX_AFFECTED_IDS]})


@router.get("", response_model=CalibrationPage, summary="The patient's calibrations, newest measurement first",
            responses={400: {"description": "cursor is not a next_cursor of this API"}})
def list_calibrations(patient_id: str, db: Db, caller: Caller, leg: Leg | None = None,
                      limit: int = Query(50, ge=1, le=200),
                      cursor: str | None = Query(None, description="next_cursor of the previous page")
                      ) -> CalibrationPage:
    """A patient's calibrations (optionally of one leg), newest measurement first, one page at a time."""
    patient = get_patient_for(db, caller, patient_id)
    stmt = calibrations_of(patient.id, leg)
    if cursor:
        # Newest first: "after" the cursor means measured earlier, so the keyset condition is mirrored.
        measured, cid = decode_cursor(cursor)
        stmt = stmt.where(or_(KneeCalibration.measured_at < measured,
                              and_(KneeCalibration.measured_at == measured, KneeCalibration.id < cid)))
    rows = db.scalars(stmt.limit(limit + 1)).all()
    page = rows[:limit]
    next_cursor = encode_cursor(page[-1].measured_at, page[-1].id) if len(rows) > limit else None
    return CalibrationPage(items=[CalibrationOut.model_validate(c) for c in page], next_cursor=next_cursor)


@router.get("/{calibration_id}", response_model=CalibrationOut, summary="One calibration")
def get_calibration(patient_id: str, calibration_id: str, db: Db, caller: Caller) -> CalibrationOut:
    """One calibration of a patient the caller may see."""
    patient = get_patient_for(db, caller, patient_id)
    return CalibrationOut.model_validate(_calibration_of(db, patient.id, calibration_id))


@router.delete("/{calibration_id}", status_code=204, response_class=Response,
               responses={204: {"headers": {AFFECTED_HEADER: {
                   "description": "Processed sessions of that leg a reprocess would now change",
                   "schema": {"type": "integer"}}}},
                          403: {"description": "Device tokens may not delete calibrations"}},
               summary="Delete a calibration (clinician/admin); processed sessions keep it until reprocessed")
def delete_calibration(patient_id: str, calibration_id: str, db: Db, caller: Caller) -> Response:
    """Delete a calibration; the sessions processed with it keep their results until they are reprocessed."""
    require_role(caller, Role.admin, Role.clinician, action="delete calibrations")
    patient = get_patient_for(db, caller, patient_id)
    cal = _calibration_of(db, patient.id, calibration_id)
    leg, measured_at = cal.leg, cal.measured_at
    db.delete(cal)
    db.flush()
    affected = affected_sessions(db, patient.id, leg, measured_at)
    db.commit()
    log.info("calibration %s of patient %s deleted by token %s; %d session(s) affected", calibration_id,
             patient.id, caller.token_id, len(affected))
    return Response(status_code=204, headers={AFFECTED_HEADER: str(len(affected))})


def _calibration_of(db: Db, patient_id: str, calibration_id: str) -> KneeCalibration:
    cal = db.get(KneeCalibration, calibration_id) if storable_key(calibration_id) else None
    if cal is None or cal.patient_id != patient_id:
        raise not_found("Calibration")
    return cal
