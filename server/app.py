"""The FastAPI application: routers, problem+json errors, body limit, and the embedded job runner."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from starlette.middleware.gzip import GZipMiddleware

from server.api import clinicians, compare, health, patients, results, sessions
from server.api.body_limit import BodyLimitMiddleware
from server.config import Settings, get_settings
from server.db import make_engine, make_sessionmaker
from server.errors import install_error_handlers
from server.trends import router as trends_router
from server.ui import routes as ui_routes

log = logging.getLogger("gaitmon.api")

DESCRIPTION = """Gait monitoring backend: tele-rehabilitation apps upload thigh and shank IMU batches, the server
computes knee flexion per stride, clinicians read results and longitudinal trends.

Every `/v1` call needs `Authorization: Bearer <token>`. Errors are RFC 9457 `application/problem+json`."""

TAGS = [
    {"name": "clinicians and tokens", "description": "Who am I, clinicians (admin), token revocation"},
    {"name": "patients", "description": "Patients of the calling clinician and their device tokens"},
    {"name": "sessions and upload", "description": "Recording sessions and idempotent batch upload"},
    {"name": "results", "description": "Strides and the continuous knee angle of a processed session"},
    {"name": "trends", "description": "Longitudinal trends per patient"},
    {"name": "health", "description": "Service and database health"},
]


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    engine = make_engine(settings.resolved_database_url)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        handle = None
        if settings.resolved_job_runner == "embedded":
            from server.jobs import embedded

            handle = embedded.start(app.state.sessionmaker, settings)
        try:
            yield
        finally:
            if handle is not None:
                handle.stop()
            engine.dispose()

    app = FastAPI(title="gaitmon", version="1.0.0", description=DESCRIPTION, openapi_tags=TAGS,
                  lifespan=lifespan)
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessionmaker = make_sessionmaker(engine)
    install_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=settings.max_body_bytes)
    # Responses too: a full-resolution knee-angle trace or an export is mostly digits and shrinks ~4x.
    app.add_middleware(GZipMiddleware, minimum_size=1024)
    app.include_router(health.router)
    app.include_router(clinicians.router)
    app.include_router(patients.router)
    app.include_router(sessions.router)
    app.include_router(results.router)
    # Routers of other modules are included below this line (one line each).
    app.include_router(trends_router.router)
    app.include_router(compare.router)
    app.include_router(ui_routes.router)
    app.mount("/ui/static", StaticFiles(directory=ui_routes.STATIC_DIR), name="ui-static")
    return app
