"""Bearer tokens (only their SHA-256 is stored), the caller's identity, and who may see which patient.

Access rule of the contract: 401 without a valid token; 403 when the caller's role may never do the thing;
404 when the resource exists but belongs to someone else (the caller may not learn that it exists).
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass

from sqlalchemy import BindParameter, ColumnElement, String, bindparam, exists, false, select, true
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Clinician, Token
from server.db import storable_key
from server.enums import Role
from server.errors import forbidden, not_found
from server.patients.models import Patient
from server.sessions.models import Session

TOKEN_PREFIX = "gm_"


def hash_token(plaintext: str) -> str:
    """The SHA-256 hex digest under which a token is stored."""
    return hashlib.sha256(plaintext.encode("utf-8")).hexdigest()


def issue_token(db: DbSession, *, role: str, name: str | None = None, clinician_id: str | None = None,
                patient_id: str | None = None) -> tuple[Token, str]:
    """Create a token row and return it with its plaintext (shown once; only the hash is stored). Flushes."""
    if role not in set(Role):
        raise ValueError(f"unknown role {role!r}")
    if role == Role.device and not patient_id:
        raise ValueError("a device token needs a patient_id")
    if role == Role.clinician and not clinician_id:
        raise ValueError("a clinician token needs a clinician_id")
    plaintext = TOKEN_PREFIX + secrets.token_urlsafe(32)
    token = Token(token_hash=hash_token(plaintext), role=role, name=name, clinician_id=clinician_id,
                  patient_id=patient_id)
    db.add(token)
    db.flush()
    return token, plaintext


def create_clinician(db: DbSession, name: str, email: str | None = None) -> tuple[Clinician, str]:
    """A clinician and its first token (plaintext returned once). Flushes; the caller commits."""
    clinician = Clinician(name=name, email=email)
    db.add(clinician)
    db.flush()
    _, plaintext = issue_token(db, role=Role.clinician, name=name, clinician_id=clinician.id)
    return clinician, plaintext


@dataclass(frozen=True)
class Principal:
    """Who is calling: the token's identity (never the plaintext)."""

    token_id: str
    role: str
    name: str | None
    clinician_id: str | None
    patient_id: str | None

    @property
    def is_admin(self) -> bool:
        return self.role == Role.admin


def require_role(principal: Principal, *roles: str, action: str) -> None:
    """403 unless the caller's role is one of ``roles``."""
    if principal.role not in roles:
        raise forbidden(f"A {principal.role} token may not {action}")


def can_access_patient(principal: Principal, patient: Patient) -> bool:
    """Whether the caller may see the patient: admins all, clinicians their own, devices theirs."""
    if principal.role == Role.admin:
        return True
    if principal.role == Role.clinician:
        return patient.clinician_id is not None and patient.clinician_id == principal.clinician_id
    return principal.role == Role.device and patient.id == principal.patient_id


def get_patient_for(db: DbSession, principal: Principal, patient_id: str) -> Patient:
    """The patient if the caller may see it, else 404 (also when it exists but is someone else's)."""
    patient = db.get(Patient, patient_id) if storable_key(patient_id) else None
    if patient is None or not can_access_patient(principal, patient):
        raise not_found("Patient")
    return patient


def get_session_for(db: DbSession, principal: Principal, session_id: str, *, for_update: bool = False) -> Session:
    """The session if the caller may see its patient, else 404. ``for_update`` locks the row (PostgreSQL)."""
    if not storable_key(session_id):
        raise not_found("Session")
    stmt = select(Session).where(Session.id == session_id)
    if for_update:
        stmt = stmt.with_for_update()
    session = db.scalar(stmt)
    if session is None:
        raise not_found("Session")
    if principal.role == Role.device:
        ok = session.patient_id == principal.patient_id
    elif principal.role == Role.admin:
        ok = True
    else:
        patient = db.get(Patient, session.patient_id)
        ok = patient is not None and can_access_patient(principal, patient)
    if not ok:
        raise not_found("Session")
    return session


def principal_for_token(db: DbSession, plaintext: str) -> Principal | None:
    """The identity behind a bearer token's plaintext, or None when it is unknown or revoked."""
    return principal_for_token_hash(db, hash_token(plaintext.strip()))


def principal_for_token_hash(db: DbSession, token_hash: str) -> Principal | None:
    """The identity behind a token's SHA-256, or None when it is unknown or revoked."""
    row = db.execute(select(Token.id, Token.role, Token.name, Token.clinician_id, Token.patient_id, Token.revoked_at)
                     .where(Token.token_hash == token_hash)).first()
    if row is None or row.revoked_at is not None:
        return None
    return Principal(token_id=row.id, role=row.role, name=row.name, clinician_id=row.clinician_id,
                     patient_id=row.patient_id)


def token_is_live(token_id: str | BindParameter[str]) -> ColumnElement[bool]:
    """SQL: the token still exists and is not revoked (checked inside the statement that relies on it)."""
    return exists().where(Token.id == token_id, Token.revoked_at.is_(None))


def session_visible_to_role(role: str) -> ColumnElement[bool]:
    """SQL on ``sessions``: a caller of this role may see the session (the rule of :func:`get_session_for`), the
    caller bound as ``:visible_patient_id`` / ``:visible_clinician_id`` (:func:`visibility_params`)."""
    if role == Role.admin:
        return true()
    if role == Role.clinician:
        return Session.patient_id.in_(
            select(Patient.id).where(Patient.clinician_id == bindparam("visible_clinician_id", type_=String)))
    if role == Role.device:
        return Session.patient_id == bindparam("visible_patient_id", type_=String)
    return false()


def visibility_params(principal: Principal) -> dict[str, str | None]:
    """The values :func:`session_visible_to_role` binds."""
    return {"visible_patient_id": principal.patient_id, "visible_clinician_id": principal.clinician_id}


def session_visible_to(principal: Principal) -> ColumnElement[bool]:
    """SQL on ``sessions``: the caller may see the session, with the caller's ids as values."""
    if principal.role == Role.admin:
        return true()
    if principal.role == Role.clinician and principal.clinician_id is not None:
        return Session.patient_id.in_(select(Patient.id).where(Patient.clinician_id == principal.clinician_id))
    if principal.role == Role.device and principal.patient_id is not None:
        return Session.patient_id == principal.patient_id
    return false()
