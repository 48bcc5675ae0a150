"""The FastAPI dependencies every router uses: the request's database session, the settings, the caller.

Connections are never held across a thread hop: the caller is resolved in a transaction of its own that returns
its connection before the route runs, routes end their transaction before they return (:func:`ended`), and the
request's session is opened on the event loop without a thread (creating it does no I/O).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from contextlib import contextmanager
from typing import Annotated

import anyio
from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session as DbSession

from server.auth.service import Principal, hash_token, principal_for_token, principal_for_token_hash
from server.config import Settings
from server.errors import ProblemError
from server.ttl_cache import TtlCache

# Teardown of a session a route left in a transaction: its own thread, never one a route is waiting for.
_TEARDOWN_LIMITER = anyio.CapacityLimiter(8)


async def get_db(request: Request) -> AsyncIterator[DbSession]:
    """One ORM session per request, from the app's sessionmaker; closed (transaction ended) at teardown."""
    db = request.app.state.sessionmaker()
    try:
        yield db
    finally:
        if db.in_transaction():
            await anyio.to_thread.run_sync(db.close, limiter=_TEARDOWN_LIMITER)
        else:
            db.close()


@contextmanager
def ended(db: DbSession) -> Iterator[DbSession]:
    """End ``db``'s transaction when the block exits, so its connection (and any row lock) is back in the pool
    before the response is serialised and sent."""
    try:
        yield db
    finally:
        db.close()


async def get_app_settings(request: Request) -> Settings:
    """The settings the app was created with."""
    return request.app.state.settings


def _unauthorized(detail: str) -> ProblemError:
    return ProblemError(401, detail, slug="unauthorized", headers={"WWW-Authenticate": 'Bearer realm="gaitmon"'})


# Declares the scheme in the OpenAPI document (Swagger's "Authorize"); the 401 problems below stay ours.
bearer_scheme = HTTPBearer(scheme_name="bearerAuth", auto_error=False,
                           description="A token from `gaitmon create-token`, POST /v1/clinicians or "
                                       "POST /v1/patients/{patient_id}/device-tokens")


def _lookup_principal(request: Request, plaintext: str) -> Principal | None:
    with request.app.state.sessionmaker() as db:
        return principal_for_token(db, plaintext)


def _lookup_principal_by_hash(request: Request, token_hash: str) -> Principal | None:
    with request.app.state.sessionmaker() as db:
        return principal_for_token_hash(db, token_hash)


def _bearer_value(request: Request, credentials: HTTPAuthorizationCredentials | None) -> str:
    value = credentials.credentials.strip() if credentials is not None else ""
    if not value:
        if not request.headers.get("authorization", ""):
            raise _unauthorized("Missing Authorization header (expected 'Bearer <token>')")
        raise _unauthorized("Authorization header must be 'Bearer <token>'")
    return value


async def current_principal(request: Request,
                            credentials: HTTPAuthorizationCredentials | None = Security(bearer_scheme)) -> Principal:
    """The caller of a /v1 endpoint, or 401.

    The token is read in a short transaction of its own whose connection is back in the pool when this returns,
    so no request holds a connection while it waits for a thread.
    """
    principal = await anyio.to_thread.run_sync(_lookup_principal, request, _bearer_value(request, credentials))
    if principal is None:
        raise _unauthorized("Invalid or revoked token")
    return principal


# How long a process remembers who a token is (role, patient, clinician never change for a token). Revocation is
# not remembered: the statement that relies on the token checks it (:func:`server.auth.service.token_is_live`).
TOKEN_IDENTITY_TTL_S = 60.0


def app_cache(request: Request, name: str, ttl_s: float) -> TtlCache:
    """A cache of this app (per process), created on first use."""
    cache = getattr(request.app.state, name, None)
    if cache is None:
        cache = TtlCache(ttl_s)
        setattr(request.app.state, name, cache)
    return cache


async def token_identity(request: Request,
                         credentials: HTTPAuthorizationCredentials | None = Security(bearer_scheme)) -> Principal:
    """The caller, for endpoints whose own statement re-checks that the token is live (batch upload), or 401.

    Known tokens are remembered for :data:`TOKEN_IDENTITY_TTL_S`, so the hot path needs no query for them.
    """
    key = hash_token(_bearer_value(request, credentials))
    cache = app_cache(request, "token_identities", TOKEN_IDENTITY_TTL_S)
    principal = cache.get(key)
    if principal is None:
        principal = await anyio.to_thread.run_sync(_lookup_principal_by_hash, request, key)
        if principal is None:
            raise _unauthorized("Invalid or revoked token")
        cache.put(key, principal)
    return principal


def unauthorized_token() -> ProblemError:
    """The 401 of a token found revoked (or deleted) by the statement that used it."""
    return _unauthorized("Invalid or revoked token")


Db = Annotated[DbSession, Depends(get_db)]
Caller = Annotated[Principal, Depends(current_principal)]
UploadCaller = Annotated[Principal, Depends(token_identity)]
AppSettings = Annotated[Settings, Depends(get_app_settings)]
