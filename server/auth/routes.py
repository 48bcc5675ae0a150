"""Who am I, clinicians (admin) and token revocation."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Query, Response
from sqlalchemy import select

from server.auth.models import Clinician, Token
from server.auth.schemas import ClinicianCreated, ClinicianIn, ClinicianOut, MeOut, TokenOut
from server.auth.service import create_clinician, require_role
from server.deps import Caller, Db
from server.enums import Role
from server.errors import not_found
from server.patients.models import Patient
from server.utc import utcnow

log = logging.getLogger("gaitmon.api")
router = APIRouter(prefix="/v1", tags=["clinicians and tokens"])


@router.get("/me", response_model=MeOut, operation_id="getMe", summary="The identity behind the bearer token")
def me(caller: Caller) -> MeOut:
    """The identity behind the bearer token."""
    return MeOut(token_id=caller.token_id, role=Role(caller.role), name=caller.name,
                 clinician_id=caller.clinician_id, patient_id=caller.patient_id)


@router.post("/clinicians", status_code=201, response_model=ClinicianCreated, operation_id="createClinician",
             responses={403: {"description": "Only an admin token may create clinicians"}},
             summary="Create a clinician and its first token (admin; the token is shown once)")
def post_clinician(body: ClinicianIn, db: Db, caller: Caller) -> ClinicianCreated:
    """Create a clinician and its first token (admin only)."""
    require_role(caller, Role.admin, action="create clinicians")
    clinician, plaintext = create_clinician(db, body.name, body.email)
    token_id = db.scalar(select(Token.id).where(Token.clinician_id == clinician.id, Token.role == Role.clinician))
    db.commit()
    log.info("clinician %s created by token %s", clinician.id, caller.token_id)
    return ClinicianCreated(id=clinician.id, name=clinician.name, email=clinician.email,
                            created_at=clinician.created_at, token=plaintext, token_id=token_id or "")


@router.get("/clinicians", response_model=list[ClinicianOut], summary="All clinicians (admin)",
            responses={403: {"description": "Only an admin token may list clinicians"}})
def list_clinicians(db: Db, caller: Caller, limit: int = Query(200, ge=1, le=1000)) -> list[ClinicianOut]:
    """Every clinician (admin only)."""
    require_role(caller, Role.admin, action="list clinicians")
    rows = db.scalars(select(Clinician).order_by(Clinician.created_at, Clinician.id).limit(limit)).all()
    return [ClinicianOut.model_validate(c) for c in rows]


def token_out(t: Token) -> TokenOut:
    """The response form of a token's metadata."""
    return TokenOut.model_validate(t)


@router.delete("/tokens/{token_id}", status_code=204, response_class=Response,
               responses={403: {"description": "Device tokens may not revoke tokens"}},
               summary="Revoke a token (admin: any; clinician: its own and its patients' device tokens)")
def revoke_token(token_id: str, db: Db, caller: Caller) -> Response:
    """Revoke a token: an admin any, a clinician its own and its patients' device tokens."""
    require_role(caller, Role.admin, Role.clinician, action="revoke tokens")
    token = db.get(Token, token_id)
    if token is None:
        raise not_found("Token")
    if caller.role == Role.clinician:
        own = token.role == Role.clinician and token.clinician_id == caller.clinician_id
        patients_device = False
        if token.role == Role.device and token.patient_id:
            patient = db.get(Patient, token.patient_id)
            patients_device = patient is not None and patient.clinician_id == caller.clinician_id
        if not (own or patients_device):
            raise not_found("Token")
    if token.revoked_at is None:
        token.revoked_at = utcnow()
        db.commit()
        log.info("token %s revoked by token %s", token.id, caller.token_id)
    return Response(status_code=204)
