"""uvicorn's HTTP/1.1 protocol, answering a request it cannot parse with a problem document.

A malformed request line or header (a bare LF, a space in a header name, a bad chunk size) is refused by the HTTP
parser before any ASGI app runs. uvicorn answers it with a plain-text 400; clients of this API read every error as
RFC 9457 problem details, so this protocol writes one instead. The connection is closed either way: after a parse
error nothing more on it can be trusted. Pass the class to uvicorn as ``http=`` (``gaitmon serve`` does;
``uvicorn --http server.http_protocol:ProblemHttpProtocol`` for several processes).
"""

from __future__ import annotations

import json

from uvicorn.protocols.http.auto import AutoHTTPProtocol

from server.errors import PROBLEM_JSON, problem_body

MALFORMED_DETAIL = "The request is not valid HTTP/1.1 (request line, header or chunk framing); the connection is closed"


def malformed_request_response(default_headers: list[tuple[bytes, bytes]]) -> bytes:
    """The bytes of the 400 problem response for an unparseable request, ``default_headers`` (server, date) first."""
    body = json.dumps(problem_body(400, MALFORMED_DETAIL, title="Malformed request", slug="malformed-request")).encode()
    lines = [b"HTTP/1.1 400 Bad Request"]
    lines += [name + b": " + value for name, value in default_headers]
    lines += [b"content-type: " + PROBLEM_JSON.encode(), b"content-length: " + str(len(body)).encode(),
              b"connection: close"]
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


class ProblemHttpProtocol(AutoHTTPProtocol):  # type: ignore[misc,valid-type]
    """uvicorn's default HTTP/1.1 protocol (httptools when installed, else h11) with a problem-details 400."""

    def send_400_response(self, msg: str) -> None:
        self.transport.write(malformed_request_response(self.server_state.default_headers))
        self.transport.close()
