"""Operations around the API: request ids, logging, Prometheus metrics, rate limits and CORS.

:func:`install` wires them into an app; each module has one job and can be read on its own.
"""

from __future__ import annotations

from fastapi import FastAPI
from starlette.middleware.cors import CORSMiddleware

from server.config import Settings


def install(app: FastAPI, settings: Settings) -> None:
    """Add the operational middleware and the ``/metrics`` route (call after the other middleware is added).

    Starlette runs the middleware added last first, so the order of the calls below is, from the outside in:
    request id (every response carries one, also a 429 or a 413), metrics (they count the 429s), CORS (a
    preflight never needs a token), rate limits.
    """
    from server.ops import metrics, rate_limit, request_id

    rate_limit.install(app, settings)
    origins = settings.cors_origin_list
    if origins:
        app.add_middleware(CORSMiddleware, allow_origins=origins, allow_methods=["*"],
                           allow_headers=["Authorization", "Content-Type", "Content-Encoding", "X-Request-ID"],
                           expose_headers=["X-Request-ID", "Retry-After", "Location"], max_age=600)
    if settings.metrics_enabled:
        metrics.install(app, settings)
    app.add_middleware(request_id.RequestIdMiddleware)
