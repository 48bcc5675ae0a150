"""Prometheus metrics (``prometheus-client``): HTTP traffic per route template, ingest, queue depth and jobs.

- ``gaitmon_http_requests_total{method,route,status}`` and ``gaitmon_http_request_duration_seconds{method,route}``:
  the route is the template (``/v1/sessions/{session_id}/batches``), never the raw path, so ids do not multiply
  the series; paths no route matches count as ``<unmatched>``.
- ``gaitmon_batches_total{result=stored|duplicate}``, ``gaitmon_samples_ingested_total``.
- ``gaitmon_jobs_total{outcome=done|failed|interrupted|lost}``, ``gaitmon_job_duration_seconds{outcome}``: counted
  by the process that runs the job (the API process with the embedded runner, else each ``gaitmon worker``).
- ``gaitmon_sessions_in_queue{status=queued|processing}``: read from the database at every scrape, so it is the
  same whichever process answers.

Several API processes (uvicorn/gunicorn workers) each count their own requests: set ``PROMETHEUS_MULTIPROC_DIR``
to an empty directory shared by them (prometheus-client's multiprocess mode) and ``/metrics`` sums all of them.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import Response
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    REGISTRY,
    CollectorRegistry,
    Counter,
    Histogram,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily
from sqlalchemy import func, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker
from starlette.middleware import Middleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.config import Settings
from server.sessions.models import Session

# The *_created series double the output and say nothing a counter's reset does not.
disable_created_metrics()

log = logging.getLogger("gaitmon.api")

UNMATCHED = "<unmatched>"
_HOLDER = "gaitmon.metrics.route"
QUEUE_STATUSES = ("queued", "processing")
# Series whose children the middleware remembers (methods are whatever clients send: bounded).
MAX_CACHED_SERIES = 1000

HTTP_REQUESTS = Counter("gaitmon_http_requests_total", "HTTP requests by route template and status",
                        ["method", "route", "status"])
HTTP_DURATION = Histogram("gaitmon_http_request_duration_seconds", "HTTP request latency by route template",
                          ["method", "route"],
                          buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0))
BATCHES = Counter("gaitmon_batches_total", "Uploaded batches (stored, or acknowledged duplicates)", ["result"])
SAMPLES = Counter("gaitmon_samples_ingested_total", "Samples stored from uploaded batches")
JOBS = Counter("gaitmon_jobs_total", "Processing jobs finished by outcome", ["outcome"])
JOB_DURATION = Histogram("gaitmon_job_duration_seconds", "Processing time of a session", ["outcome"],
                         buckets=(0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0))


# The children of the counters every upload touches, looked up once (labels() validates and locks each time).
_BATCHES_STORED = BATCHES.labels(result="stored")
_BATCHES_DUPLICATE = BATCHES.labels(result="duplicate")


def batch_ingested(samples: int, *, stored: bool) -> None:
    """Count one accepted batch (``stored`` False: an identical replay that was acknowledged)."""
    if stored:
        _BATCHES_STORED.inc()
        SAMPLES.inc(samples)
    else:
        _BATCHES_DUPLICATE.inc()


def job_finished(outcome: str, seconds: float) -> None:
    """Count one processing job that ran (outcome "done", "failed", "interrupted" or "lost")."""
    JOBS.labels(outcome=outcome).inc()
    JOB_DURATION.labels(outcome=outcome).observe(seconds)


class QueueDepthCollector:
    """Sessions waiting for or in processing, counted in the database at scrape time."""

    def __init__(self, sm: sessionmaker[DbSession]) -> None:
        self._sm = sm

    def collect(self):  # noqa: ANN201 - prometheus-client's collector protocol
        try:
            with self._sm() as db:
                rows = dict(db.execute(select(Session.status, func.count())
                                       .where(Session.status.in_(QUEUE_STATUSES)).group_by(Session.status)).all())
        except SQLAlchemyError as exc:
            # The rest of /metrics stays useful while the database is away (/healthz reports that).
            log.warning("metrics: queue depth unavailable: %s", type(exc).__name__)
            return
        g = GaugeMetricFamily("gaitmon_sessions_in_queue", "Sessions queued for or in processing", labels=["status"])
        for status in QUEUE_STATUSES:
            g.add_metric([status], float(rows.get(status, 0)))
        yield g


def route_template(scope: Scope) -> str:
    """The route template of a routed request: each path segment that is a path parameter becomes ``{name}``.

    Read from the routed scope (``path_params``), which works whatever nesting of routers matched it.
    """
    if "app_root_path" in scope:  # a mount (the docs assets): everything below its prefix is one series
        return scope["root_path"][len(scope["app_root_path"]):] + "/{path}"
    params = scope.get("path_params") or {}
    path: str = scope["path"]
    by_value = {str(v): k for k, v in params.items() if "/" not in str(v)}
    return "/".join("{" + by_value[seg] + "}" if seg in by_value else seg for seg in path.split("/"))


class _RouteRecorder:
    """Innermost middleware: after routing, writes the template into the holder the metrics middleware left.

    The outer middleware cannot read it from its own scope: middleware in between (the body limit) pass a copy on.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await self.app(scope, receive, send)
        finally:
            holder = scope.get(_HOLDER)
            if holder is not None and "endpoint" in scope:
                holder["route"] = route_template(scope)


class MetricsMiddleware:
    """Counts every HTTP request with its status and latency under its route template."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        # (method, route, status) -> the counter's and histogram's children: labels() validates and locks per call.
        self._children: dict[tuple[str, str, int], tuple[Any, Any]] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        holder: dict[str, str] = {}
        scope[_HOLDER] = holder
        status = 500
        t0 = time.perf_counter()

        async def send_and_record(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_record)
        finally:
            key = (scope["method"], holder.get("route", UNMATCHED), status)
            children = self._children.get(key)
            if children is None:
                method, route, _ = key
                children = (HTTP_REQUESTS.labels(method=method, route=route, status=str(status)),
                            HTTP_DURATION.labels(method=method, route=route))
                if len(self._children) < MAX_CACHED_SERIES:
                    self._children[key] = children
            children[0].inc()
            children[1].observe(time.perf_counter() - t0)


def render(sm: sessionmaker[DbSession]) -> bytes:
    """The exposition text: this process's metrics (or all processes' in multiprocess mode) plus queue depth."""
    queue = CollectorRegistry()
    queue.register(QueueDepthCollector(sm))
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        from prometheus_client import multiprocess

        merged = CollectorRegistry()
        multiprocess.MultiProcessCollector(merged)
        return generate_latest(merged) + generate_latest(queue)
    return generate_latest(REGISTRY) + generate_latest(queue)


def install(app: FastAPI, settings: Settings) -> None:
    """The counting middleware and ``GET /metrics`` (Prometheus text format, not in the OpenAPI document)."""
    app.add_middleware(MetricsMiddleware)
    app.user_middleware.append(Middleware(_RouteRecorder))

    def metrics_endpoint(request: Request) -> Response:
        return Response(render(request.app.state.sessionmaker), media_type=CONTENT_TYPE_LATEST)

    app.add_api_route("/metrics", metrics_endpoint, methods=["GET"], include_in_schema=False)
