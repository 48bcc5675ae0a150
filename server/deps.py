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
from fastapi import Depends, Request
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Token
from server.auth.service import Principal, hash_token
from server.config import Settings
from server.errors import ProblemError

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


def _lookup_principal(request: Request, token_hash: str) -> Principal | None:
    with request.app.state.sessionmaker() as db:
        token = db.scalar(select(Token).where(Token.token_hash == token_hash))
        if token is None or token.revoked_at is not None:
            return None
        return Principal(token_id=token.id, role=token.role, name=token.name, clinician_id=token.clinician_id,
                         patient_id=token.patient_id)


async def current_principal(request: Request) -> Principal:
    """The caller of a /v1 endpoint, or 401.

    The token is read in a short transaction of its own whose connection is back in the pool when this returns,
    so no request holds a connection while it waits for a thread.
    """
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if not header:
        raise _unauthorized("Missing Authorization header (expected 'Bearer <token>')")
    if scheme.lower() != "bearer" or not value.strip():
        raise _unauthorized("Authorization header must be 'Bearer <token>'")
    principal = await anyio.to_thread.run_sync(_lookup_principal, request, hash_token(value.strip()))
    if principal is None:
        raise _unauthorized("Invalid or revoked token")
    return principal


Db = Annotated[DbSession, Depends(get_db)]
Caller = Annotated[Principal, Depends(current_principal)]
AppSettings = Annotated[Settings, Depends(get_app_settings)]
