"""The FastAPI dependencies every router uses: the request's database session, the settings, the caller."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
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


# Declares the scheme in the OpenAPI document (Swagger's "Authorize"); the 401 problems below stay ours.
bearer_scheme = HTTPBearer(scheme_name="bearerAuth", auto_error=False,
                           description="A token from `gaitmon create-token`, POST /v1/clinicians or "
                                       "POST /v1/patients/{patient_id}/device-tokens")


def current_principal(request: Request, db: DbSession = Depends(get_db),
                      credentials: HTTPAuthorizationCredentials | None = Security(bearer_scheme)) -> Principal:
    """The caller of a /v1 endpoint, or 401."""
    value = credentials.credentials.strip() if credentials is not None else ""
    if not value:
        if not request.headers.get("authorization", ""):
            raise _unauthorized("Missing Authorization header (expected 'Bearer <token>')")
        raise _unauthorized("Authorization header must be 'Bearer <token>'")
    token = db.scalar(select(Token).where(Token.token_hash == hash_token(value)))
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
