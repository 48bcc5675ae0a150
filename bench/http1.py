"""A minimal HTTP/1.1 client for load generation on loopback: one keep-alive connection, one request at a time.

The load generator shares the machine's 2 cores with the server it measures. httpx spends about a millisecond of
CPU per request; hundreds of simulated phones in one event loop then delay every send and every answer by the
generator's own backlog, and the latencies it reports are partly its own. This client writes the request in one
``write`` and reads the answer with ``readuntil``/``readexactly``: a fraction of that cost.
"""

from __future__ import annotations

import asyncio
import gzip
import json
from dataclasses import dataclass
from typing import Any


class Http1Error(Exception):
    """The connection failed, was closed or timed out before a complete answer (the request may have arrived)."""


@dataclass(frozen=True)
class Answer:
    """A complete HTTP answer: status, headers (lower-case names) and body."""

    status_code: int
    headers: dict[str, str]
    content: bytes

    def json(self) -> Any:  # noqa: ANN401 - whatever the body holds
        return json.loads(self.content)


class Http1Connection:
    """Keep-alive HTTP/1.1 to ``host:port``; reconnects when the server closed the connection."""

    def __init__(self, host: str, port: int, timeout_s: float = 30.0) -> None:
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def request(self, method: str, path: str, *, content: bytes = b"",
                      headers: dict[str, str] | None = None) -> Answer:
        """Send one request and read its answer; :class:`Http1Error` if the connection fails or times out."""
        head = [f"{method} {path} HTTP/1.1", f"Host: {self.host}:{self.port}", f"Content-Length: {len(content)}"]
        head += [f"{k}: {v}" for k, v in (headers or {}).items()]
        data = ("\r\n".join(head) + "\r\n\r\n").encode("latin-1") + content
        try:
            async with asyncio.timeout(self.timeout_s):
                return await self._exchange(data)
        except (OSError, EOFError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError,
                ValueError) as exc:
            self.close()
            raise Http1Error(f"{method} {path}: {type(exc).__name__}: {exc}") from exc

    async def _exchange(self, data: bytes) -> Answer:
        if self._reader is None or self._writer is None or self._reader.at_eof():
            self.close()
            self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        reader, writer = self._reader, self._writer
        writer.write(data)
        head = (await reader.readuntil(b"\r\n\r\n")).decode("latin-1").split("\r\n")
        status = int(head[0].split(" ", 2)[1])
        headers: dict[str, str] = {}
        for line in head[1:]:
            if line:
                k, _, v = line.partition(":")
                headers[k.strip().lower()] = v.strip()
        if "content-length" in headers:
            body = await reader.readexactly(int(headers["content-length"]))
        elif headers.get("transfer-encoding", "").lower() == "chunked":
            body = await _read_chunked(reader)
        else:
            raise ValueError("answer without Content-Length or chunked encoding")
        if headers.get("connection", "").lower() == "close":
            self.close()
        if headers.get("content-encoding", "").lower() == "gzip":
            body = gzip.decompress(body)
        return Answer(status, headers, body)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
        self._reader = self._writer = None


async def _read_chunked(reader: asyncio.StreamReader) -> bytes:
    out = bytearray()
    while True:
        size = int((await reader.readuntil(b"\r\n")).split(b";", 1)[0], 16)
        if size == 0:
            await reader.readuntil(b"\r\n")  # no trailers from our servers: the empty line
            return bytes(out)
        out += await reader.readexactly(size)
        await reader.readexactly(2)
