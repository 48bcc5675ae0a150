"""Pure ASGI middleware: backpressure. Past ``max_in_flight`` requests in progress, a new request is answered
503 + ``Retry-After`` at once instead of queueing for a thread or a connection without bound.

Health checks are never refused, so a load balancer sees a busy process as alive.
"""

from __future__ import annotations

import json
import logging

from server.body_limit import ASGIApp, Receive, Scope, Send
from server.errors import PROBLEM_JSON, problem_body

log = logging.getLogger("gaitmon.api")

EXEMPT_PATHS = frozenset({"/healthz"})


class InFlightLimitMiddleware:
    """Answers 503 + Retry-After when more than ``max_in_flight`` requests are in progress in this process."""

    def __init__(self, app: ASGIApp, max_in_flight: int, retry_after_s: int) -> None:
        self.app = app
        self.max_in_flight = max_in_flight
        self.retry_after_s = retry_after_s
        self.in_flight = 0
        self.refused = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("path") in EXEMPT_PATHS:
            await self.app(scope, receive, send)
            return
        if self.in_flight >= self.max_in_flight:
            self.refused += 1
            if self.refused % 100 == 1:
                log.warning("%d requests in flight: refusing with 503 (%d refused so far)", self.in_flight,
                            self.refused)
            await self._refuse(scope, send)
            return
        # One event loop per process: the counter needs no lock.
        self.in_flight += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight -= 1

    async def _refuse(self, scope: Scope, send: Send) -> None:
        payload = json.dumps(problem_body(503, "The service is busy; retry after the time in Retry-After",
                                          title="Busy", slug="overloaded", instance=scope.get("path"))).encode()
        await send({"type": "http.response.start", "status": 503, "headers": [
            (b"content-type", PROBLEM_JSON.encode()), (b"content-length", str(len(payload)).encode()),
            (b"retry-after", str(self.retry_after_s).encode())]})
        await send({"type": "http.response.body", "body": payload})
