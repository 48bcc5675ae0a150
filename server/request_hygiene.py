"""Pure ASGI middleware: a request whose path or query string holds text no database can store gets 422.

Path ids and query values (cursors, filters) reach SQL as parameters; a NUL makes PostgreSQL fail the statement.
Checked once here for every route instead of on each parameter; string fields of JSON bodies are checked by
:class:`server.schema_types.StrictIn`.
"""

from __future__ import annotations

import json
from urllib.parse import unquote_plus

from starlette.requests import Request

from server.body_limit import ASGIApp, Receive, Scope, Send
from server.errors import PROBLEM_JSON, PageErrors, problem_body
from server.schema_types import text_problem


def request_text_problem(scope: Scope) -> str | None:
    """What is wrong with the path or the query string of a request, or None."""
    problem = text_problem(scope.get("path", ""))
    if problem is not None:
        return f"path: {problem}"
    query = scope.get("query_string", b"")
    if query:
        # The same decoding as Starlette's query parser (UTF-8, invalid bytes replaced).
        problem = text_problem(unquote_plus(query.decode("latin-1"), encoding="utf-8", errors="replace"))
        if problem is not None:
            return f"query: {problem}"
    return None


class RequestHygieneMiddleware:
    """422 problem for a NUL or a lone surrogate in the path or query string, before any route runs; a page's
    address gets the page from ``page_errors`` instead."""

    def __init__(self, app: ASGIApp, page_errors: PageErrors | None = None) -> None:
        self.app = app
        self.page_errors = page_errors

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        problem = request_text_problem(scope)
        if problem is None:
            await self.app(scope, receive, send)
            return
        page = self.page_errors(Request(scope), 422, problem) if self.page_errors is not None else None
        if page is not None:
            await page(scope, receive, send)
            return
        field, _, message = problem.partition(": ")
        body = problem_body(422, problem, title="Validation failed", slug="validation-error",
                            instance=scope.get("path", "").replace("\x00", "\\0"),
                            errors=[{"field": field, "message": message}])
        payload = json.dumps(body).encode()
        await send({"type": "http.response.start", "status": 422,
                    "headers": [(b"content-type", PROBLEM_JSON.encode()),
                                (b"content-length", str(len(payload)).encode())]})
        await send({"type": "http.response.body", "body": payload})
