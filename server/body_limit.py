"""Pure ASGI middleware: request body size limit applied AFTER gzip decompression, and JSON-only bodies on /v1.

The body is read chunk by chunk and inflated with ``zlib.decompressobj(...).decompress(data, max_length)``, so
a gzip bomb stops at ``max_body_bytes + 1`` inflated bytes and answers 413 instead of filling memory. The app
behind sees an ordinary (decompressed) body without ``Content-Encoding``. A body that inflates to at most
:data:`INLINE_INFLATE_MAX_BYTES` (a phone's batch: a few kB) is inflated on the event loop, which costs less than
the thread hop; a larger one in a worker thread, so it cannot hold the loop. Gzip members are capped too.

A non-empty body sent to ``/v1`` must say ``Content-Type: application/json`` (or ``+json``): 415 otherwise.
"""

from __future__ import annotations

import json
import logging
import zlib
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

import anyio

from server.errors import PROBLEM_JSON, problem_body

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

log = logging.getLogger("gaitmon.api")

BODY_METHODS = {"POST", "PUT", "PATCH", "DELETE"}
JSON_ONLY_PREFIX = "/v1/"
SMALL_JSON_MAX_BYTES = 64 * 1024
"""Largest body of a ``/v1`` request other than a batch upload (a patient, a session, a calibration: well under a
kB). ``max_body_bytes`` is sized for batches; a body of ~700k unknown keys under it cost seconds and a gigabyte of
validation errors."""
# Concatenated gzip members accepted in one body: an app sends one; thousands of empty ones are an attack.
MAX_GZIP_MEMBERS = 64
# Inflated on the event loop up to this many bytes (~0.5 ms of zlib at worst); past it, in a worker thread.
INLINE_INFLATE_MAX_BYTES = 256 * 1024


def is_json_media_type(content_type: str) -> bool:
    """``application/json`` or a ``+json`` type, parameters (charset) ignored."""
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


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
        self._members = 1

    def feed(self, data: bytes) -> None:
        pending = data
        while pending:
            self._seen_input = True
            if self._d.eof:
                # Another gzip member follows the previous one (RFC 1952 allows concatenation).
                self._members += 1
                if self._members > MAX_GZIP_MEMBERS:
                    raise _Reject(400, f"Request body has more than {MAX_GZIP_MEMBERS} gzip members")
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

    def __init__(self, app: ASGIApp, max_body_bytes: int, body_timeout_s: float = 15.0) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.body_timeout_s = body_timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in BODY_METHODS:
            await self.app(scope, receive, send)
            return
        headers = [(k.lower(), v) for k, v in scope.get("headers", [])]
        encoding = next((v.decode("latin-1").strip().lower() for k, v in headers if k == b"content-encoding"), "")
        try:
            if scope.get("path", "").startswith(JSON_ONLY_PREFIX) and _announces_body(headers):
                content_type = next((v.decode("latin-1") for k, v in headers if k == b"content-type"), "")
                if not is_json_media_type(content_type):
                    raise _Reject(415, f"Content-Type must be application/json (got {content_type[:100]!r})")
            body = await self._read_body(headers, encoding, receive)
            path = scope.get("path", "")
            if path.startswith(JSON_ONLY_PREFIX) and not path.endswith("/batches") \
                    and len(body) > SMALL_JSON_MAX_BYTES:
                raise _Reject(413, f"Request body exceeds the limit of {SMALL_JSON_MAX_BYTES} bytes for this "
                                   "endpoint (only batch uploads may be larger)")
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
        gzipped = encoding in ("gzip", "x-gzip")
        raw = bytearray()
        received = 0
        # the request already holds one of the in-flight slots: a body that trickles in or never ends must not keep it
        with anyio.move_on_after(self.body_timeout_s) as scope:
            while True:
                message = await receive()
                if message["type"] == "http.disconnect":
                    raise _Reject(400, "Client disconnected before the body was complete")
                chunk = message.get("body", b"")
                received += len(chunk)
                if received > self.max_body_bytes:
                    raise _Reject(413, f"Request body exceeds the limit of {self.max_body_bytes} bytes")
                raw += chunk
                if not message.get("more_body", False):
                    break
        if scope.cancelled_caught:
            raise _Reject(408, f"The request body did not arrive within {self.body_timeout_s:g} s")
        if not gzipped:
            return bytes(raw)
        return await self._inflated(raw)

    async def _inflated(self, raw: bytearray) -> bytes:
        inline_limit = min(self.max_body_bytes, INLINE_INFLATE_MAX_BYTES)
        if len(raw) <= inline_limit:
            try:
                return _inflate(raw, inline_limit)
            except _Reject as rej:
                if rej.status != 413 or inline_limit == self.max_body_bytes:
                    raise
                # Inflates past the inline budget: start again in a worker thread with the real limit.
        # The compressed body is at most max_body_bytes; inflating it is CPU work that must not hold the loop.
        return await anyio.to_thread.run_sync(_inflate, bytes(raw), self.max_body_bytes)


def _announces_body(headers: list[tuple[bytes, bytes]]) -> bool:
    """Whether the request has a body (HTTP/1.1: a positive Content-Length or a Transfer-Encoding)."""
    for k, v in headers:
        if k == b"transfer-encoding":
            return True
        if k == b"content-length":
            return v.strip() not in (b"0", b"")
    return False


def _inflate(data: bytes | bytearray, limit: int) -> bytes:
    inflater = _GzipInflater(limit)
    inflater.feed(data)
    return inflater.finish()


async def _send_problem(scope: Scope, send: Send, status: int, detail: str) -> None:
    payload = json.dumps(problem_body(status, detail, instance=scope.get("path"))).encode()
    headers = [(b"content-type", PROBLEM_JSON.encode()), (b"content-length", str(len(payload)).encode())]
    if status in (408, 413, 415):
        # The rest of the body was not read: the client must not reuse the connection.
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": payload})
