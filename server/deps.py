"""The FastAPI dependencies every router uses: the request's database session, the settings, the caller."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Token
from server.auth.service import Principal, hash_token
from server.config import Settings
from server.errors import ProblemError


def get_db(request: Request) -> Iterator[DbSession]:
    """One ORM session per request, from the app's sessionmaker."""
    with request.app.state.sessionmaker() as db:
        yield db


async def get_app_settings(request: Request) -> Settings:
    """The settings the app was created with."""
    return request.app.state.settings


def _unauthorized(detail: str) -> ProblemError:
    return ProblemError(401, detail, slug="unauthorized", headers={"WWW-Authenticate": 'Bearer realm="gaitmon"'})


def current_principal(request: Request, db: DbSession = Depends(get_db)) -> Principal:
    """The caller of a /v1 endpoint, or 401."""
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if not header:
        raise _unauthorized("Missing Authorization header (expected 'Bearer <token>')")
    if scheme.lower() != "bearer" or not value.strip():
        raise _unauthorized("Authorization header must be 'Bearer <token>'")
    token = db.scalar(select(Token).where(Token.token_hash == hash_token(value.strip())))
    if token is None or token.revoked_at is not None:
        raise _unauthorized("Invalid or revoked token")
    principal = Principal(token_id=token.id, role=token.role, name=token.name, clinician_id=token.clinician_id,
                          patient_id=token.patient_id)
    # End the read: a route that computes for long (compare) must not hold a pooled connection meanwhile.
    db.rollback()
    return principal


Db = Annotated[DbSession, Depends(get_db)]
Caller = Annotated[Principal, Depends(current_principal)]
AppSettings = Annotated[Settings, Depends(get_app_settings)]
