"""Liveness with a database check (no auth): for load balancers and docker-compose health checks."""

from __future__ import annotations

import logging

import anyio
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from sqlalchemy import text
from sqlalchemy.engine import Engine

from server.errors import problem_response

log = logging.getLogger("gaitmon.api")
router = APIRouter(tags=["health"])
# Health checks get threads of their own: under load they must not queue behind the routes' thread pool.
_HEALTH_LIMITER = anyio.CapacityLimiter(2)


class HealthOut(BaseModel):
    """The service and its database answer."""

    status: str
    database: str


@router.get("/healthz", response_model=HealthOut, operation_id="getHealth",
            summary="200 when the service and its database answer, else 503",
            responses={503: {"description": "The database does not answer"}})
async def healthz(request: Request) -> JSONResponse:
    """200 when the service and its database answer, 503 otherwise."""
    try:
        await anyio.to_thread.run_sync(_ping, request.app.state.engine, limiter=_HEALTH_LIMITER)
    except Exception as exc:  # noqa: BLE001 - any failure to reach the database means "not healthy"
        log.warning("health check: database unavailable: %s", type(exc).__name__)
        return problem_response(503, "The database does not answer", slug="database-unavailable",
                                instance="/healthz")
    return JSONResponse({"status": "ok", "database": "ok"})


def _ping(engine: Engine) -> None:
    with engine.connect() as conn:
        conn.execute(text("SELECT 1"))
