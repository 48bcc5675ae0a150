"""The FastAPI application: routers, problem+json errors, body limit, and the embedded job runner."""

from __future__ import annotations

import gc
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.middleware.gzip import GZipMiddleware
from starlette.types import Receive, Scope, Send

from server import health
from server import metadata as _metadata  # noqa: F401 - registers every table before the first query
from server.admission import InFlightLimitMiddleware
from server.auth import routes as auth_routes
from server.body_limit import BodyLimitMiddleware
from server.calibrations import routes as calibration_routes
from server.config import Settings, get_settings
from server.db import make_engine, make_sessionmaker, make_upload_engine
from server.errors import install_error_handlers
from server.openapi import install as install_openapi
from server.openapi import operation_id
from server.ops import install as install_ops
from server.patients import routes as patient_routes
from server.request_hygiene import RequestHygieneMiddleware
from server.results import routes as result_routes
from server.sessions import routes as session_routes
from server.sessions.group_commit import GroupCommitter
from server.trends import routes as trend_routes
from server.ui import routes as ui_routes

log = logging.getLogger("gaitmon.api")
# Whether this process has moved its start-up objects out of the collector's sight (gc.freeze) yet.
_FROZEN: list[bool] = []

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


class ResponseGZipMiddleware(GZipMiddleware):
    """Starlette's response compression, skipped for batch uploads: their answer (a BatchOut or a problem, a few
    hundred bytes) is always below ``minimum_size`` and would go out unchanged after the responder's buffering,
    ~5 % of an upload's CPU."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] == "POST" and scope["path"].endswith("/batches"):
            await self.app(scope, receive, send)
            return
        await super().__call__(scope, receive, send)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The FastAPI application: routers, error handlers, body limits and, with SQLite, the embedded job runner."""
    settings = settings or get_settings()
    engine = make_engine(settings.resolved_database_url, settings)
    upload_engine = make_upload_engine(settings.resolved_database_url, settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Sync routes run in anyio's default thread pool; no more threads than pooled connections (see
        # Settings.api_threads), so a thread that needs a connection never waits for one forever.
        anyio.to_thread.current_default_thread_limiter().total_tokens = settings.api_threads
        handle = None
        if settings.resolved_job_runner == "embedded":
            from server.processing import embedded

            handle = embedded.start(app.state.sessionmaker, settings)
        # Everything imported and built so far lives as long as the process: out of the collector's sight, a
        # full collection scans only what requests allocate (with ~1M start-up objects in view, each took
        # 0.1-0.3 s every 3-5 s at 200 uploads/s, holding the event loop and every thread).
        # Once per process (a test suite starts many apps).
        if not _FROZEN:
            _FROZEN.append(True)
            gc.collect()
            gc.freeze()
        try:
            yield
        finally:
            if handle is not None:
                handle.stop()
            engine.dispose()
            if upload_engine is not None:
                upload_engine.dispose()
            pool = getattr(app.state, "upload_pool", None)
            if pool is not None:
                app.state.upload_pool = None  # a later start makes a new one
                pool.shutdown(wait=False, cancel_futures=True)

    # /docs and /redoc with Swagger UI and ReDoc from the fastapi-offline package: no CDN, works offline.
    app = FastAPIOffline(title="gaitmon", version="1.0.0", description=DESCRIPTION, openapi_tags=TAGS,
                         generate_unique_id_function=operation_id, lifespan=lifespan,
                         swagger_ui_parameters={"validatorUrl": None})
    app.state.settings = settings
    app.state.engine = engine
    app.state.upload_engine = upload_engine
    if upload_engine is not None:
        app.state.group_committer = GroupCommitter(upload_engine, grouped=settings.upload_group_commit)
    app.state.sessionmaker = make_sessionmaker(engine)
    install_error_handlers(app, page_errors=ui_routes.page_error)
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=settings.max_body_bytes,
                       body_timeout_s=settings.body_timeout_s)
    # Responses too: a full-resolution knee-angle trace or an export is mostly digits and shrinks ~4x.
    app.add_middleware(ResponseGZipMiddleware, minimum_size=1024)
    install_ops(app, settings)
    app.add_middleware(RequestHygieneMiddleware, page_errors=ui_routes.page_error)
    # Outermost: an overloaded process refuses before reading a body or taking a thread.
    app.add_middleware(InFlightLimitMiddleware, max_in_flight=settings.max_in_flight,
                       retry_after_s=settings.retry_after_s)
    # The sessions router first: the phones' uploads are most of the traffic, and routes are matched in order.
    first_included = len(app.router.routes)
    app.include_router(session_routes.router)
    app.include_router(health.router)
    app.include_router(auth_routes.router)
    app.include_router(patient_routes.router)
    app.include_router(result_routes.router)
    # Routers of other modules are included below this line (one line each).
    app.include_router(trend_routes.router)
    app.include_router(ui_routes.router)
    app.mount("/ui/static", StaticFiles(directory=ui_routes.STATIC_DIR), name="ui-static")
    app.add_api_route("/", lambda: RedirectResponse("/ui/"), include_in_schema=False)
    app.include_router(calibration_routes.router)
    install_openapi(app)
    # ... before even the documentation routes FastAPI registers itself (each match tried costs ~10 us).
    app.router.routes.insert(0, app.router.routes.pop(first_included))
    return app
