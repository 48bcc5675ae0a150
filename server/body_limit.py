"""Pure ASGI middleware: request body size limit applied AFTER gzip decompression, streaming.

The body is read chunk by chunk and inflated with ``zlib.decompressobj(...).decompress(data, max_length)``, so
a gzip bomb stops at ``max_body_bytes + 1`` inflated bytes and answers 413 instead of filling memory. The app
behind sees an ordinary (decompressed) body without ``Content-Encoding``.
"""

from __future__ import annotations

import json
import logging
import zlib
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from server.errors import PROBLEM_JSON, problem_body

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

log = logging.getLogger("gaitmon.api")

BODY_METHODS = {"POST", "PUT", "PATCH", "DELETE"}


class _Reject(Exception):
    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


class _GzipInflater:
    """Inflates gzip input incrementally (also concatenated members), never more than ``limit + 1`` bytes."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.out = bytearray()
        self._d = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
        self._seen_input = False

    def feed(self, data: bytes) -> None:
        pending = data
        while pending:
            self._seen_input = True
            if self._d.eof:
                # Another gzip member follows the previous one (RFC 1952 allows concatenation).
                self._d = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
            # max_length >= 1 here (0 would mean unlimited): the check below raises as soon as out > limit.
            try:
                chunk = self._d.decompress(pending, self.limit + 1 - len(self.out))
            except zlib.error as exc:
                raise _Reject(400, f"Request body is not valid gzip: {exc}") from exc
            self.out += chunk
            if len(self.out) > self.limit:
                raise _Reject(413, f"Request body exceeds {self.limit} bytes after decompression")
            pending = self._d.unused_data if self._d.eof else self._d.unconsumed_tail

    def finish(self) -> bytes:
        if self._seen_input and not self._d.eof:
            raise _Reject(400, "Request body is truncated gzip")
        return bytes(self.out)


class BodyLimitMiddleware:
    """Rejects request bodies over the limit (also after gzip inflation) with a 413 problem."""

    def __init__(self, app: ASGIApp, max_body_bytes: int) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in BODY_METHODS:
            await self.app(scope, receive, send)
            return
        headers = [(k.lower(), v) for k, v in scope.get("headers", [])]
        encoding = next((v.decode("latin-1").strip().lower() for k, v in headers if k == b"content-encoding"), "")
        try:
            body = await self._read_body(headers, encoding, receive)
        except _Reject as rej:
            log.info("%s %s -> %d %s", scope["method"], scope.get("path"), rej.status, rej.detail)
            await _send_problem(scope, send, rej.status, rej.detail)
            return
        new_headers = [(k, v) for k, v in headers if k not in (b"content-encoding", b"content-length")]
        new_headers.append((b"content-length", str(len(body)).encode()))
        scope = dict(scope, headers=new_headers)
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _read_body(self, headers: list[tuple[bytes, bytes]], encoding: str, receive: Receive) -> bytes:
        if encoding not in ("", "identity", "gzip", "x-gzip"):
            raise _Reject(415, f"Content-Encoding {encoding!r} is not supported (use gzip or none)")
        length = next((v for k, v in headers if k == b"content-length"), None)
        if length is not None:
            try:
                declared = int(length)
            except ValueError as exc:
                raise _Reject(400, "Content-Length is not an integer") from exc
            # A compressed body larger than the limit is rejected too: it cannot be legitimate here.
            if declared > self.max_body_bytes:
                raise _Reject(413, f"Request body of {declared} bytes exceeds the limit of {self.max_body_bytes}")
        inflater = _GzipInflater(self.max_body_bytes) if encoding in ("gzip", "x-gzip") else None
        raw = bytearray()
        received = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                raise _Reject(400, "Client disconnected before the body was complete")
            chunk = message.get("body", b"")
            received += len(chunk)
            if received > self.max_body_bytes:
                raise _Reject(413, f"Request body exceeds the limit of {self.max_body_bytes} bytes")
            if inflater is not None:
                inflater.feed(chunk)
            else:
                raw += chunk
            if not message.get("more_body", False):
                break
        return inflater.finish() if inflater is not None else bytes(raw)


async def _send_problem(scope: Scope, send: Send, status: int, detail: str) -> None:
    payload = json.dumps(problem_body(status, detail, instance=scope.get("path"))).encode()
    headers = [(b"content-type", PROBLEM_JSON.encode()), (b"content-length", str(len(payload)).encode())]
    if status == 413:
        # The rest of the body was not read: the client must not reuse the connection.
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": payload})
