"""A request id on every response (``X-Request-ID``) and in every log line written while the request runs.

An incoming ``X-Request-ID`` is kept when it is sane (1-128 characters of ``[A-Za-z0-9._:-]``, e.g. a UUID or a
proxy's id), so one id follows a request through a load balancer; otherwise a new one is generated. The id lives in
a context variable: the logging filter reads it from the thread or task that logs, including FastAPI's thread pool
(anyio copies the context into worker threads).
"""

from __future__ import annotations

import logging
import re
import uuid
from contextvars import ContextVar

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

HEADER = "X-Request-ID"
_SANE = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")

request_id_var: ContextVar[str] = ContextVar("gaitmon_request_id", default="-")


def current_request_id() -> str:
    """The id of the request being handled, ``"-"`` outside a request."""
    return request_id_var.get()


def accept_or_generate(incoming: str | None) -> str:
    """The incoming id if it is sane, else a fresh one (32 hex digits)."""
    if incoming and _SANE.match(incoming):
        return incoming
    return uuid.uuid4().hex


class RequestIdFilter(logging.Filter):
    """Adds ``record.request_id`` (``-`` outside a request) so every formatter can print it."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = request_id_var.get()
        return True


class RequestIdMiddleware:
    """Pure ASGI middleware (no response buffering): sets the context variable and the response header."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = next((v.decode("latin-1") for k, v in scope.get("headers", []) if k == b"x-request-id"), None)
        rid = accept_or_generate(incoming)
        token = request_id_var.set(rid)

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                MutableHeaders(scope=message)[HEADER] = rid
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            request_id_var.reset(token)
