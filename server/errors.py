"""RFC 9457 problem details for every error the API returns (never a stack trace)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import partial
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.exc import OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("gaitmon.api")

PROBLEM_JSON = "application/problem+json"
# Validation errors past this many are summarised: a batch of 20 000 NaN rows must not echo 20 000 entries.
MAX_FIELD_ERRORS = 50


class ProblemFieldError(BaseModel):
    """One invalid field of a request."""

    field: str = Field(description="Where: a body path (`gyro[17][2]`), a parameter name, or `body`",
                       examples=["gyro[17][2]"])
    message: str = Field(description="What is wrong with it", examples=["Input should be a finite number"])


class Problem(BaseModel):
    """An RFC 9457 problem details document: the body of every error response (``application/problem+json``)."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [{
        "type": "urn:gaitmon:problem:validation-error", "title": "Validation failed", "status": 422,
        "detail": "gyro[17][2]: Input should be a finite number",
        "instance": "/v1/sessions/3f0c2a9e8b7d4c1a9e6f5d4c3b2a1908/batches",
        "errors": [{"field": "gyro[17][2]", "message": "Input should be a finite number"}]}]})

    type: str = Field(description="URI of the kind of problem, `urn:gaitmon:problem:<slug>`",
                      examples=["urn:gaitmon:problem:not-found"])
    title: str = Field(description="Short summary of the kind of problem", examples=["Not Found"])
    status: int = Field(description="The HTTP status code", examples=[404])
    detail: str = Field(description="What went wrong with this request", examples=["Session not found"])
    instance: str | None = Field(None, description="The request path")
    errors: list[ProblemFieldError] | None = Field(None, description="Validation problems: one entry per invalid "
                                                                     f"field (at most {MAX_FIELD_ERRORS + 1})")


def problem_type(slug: str) -> str:
    """The ``type`` URI of a problem slug."""
    return f"urn:gaitmon:problem:{slug}"


def _default_slug(status: int) -> str:
    try:
        return HTTPStatus(status).phrase.lower().replace(" ", "-").replace("'", "")
    except ValueError:
        return "error"


def problem_body(status: int, detail: str, *, title: str | None = None, slug: str | None = None,
                 instance: str | None = None, errors: list[dict[str, str]] | None = None) -> dict[str, Any]:
    """An RFC 9457 problem details body."""
    try:
        default_title = HTTPStatus(status).phrase
    except ValueError:
        default_title = "Error"
    body: dict[str, Any] = {
        "type": problem_type(slug or _default_slug(status)),
        "title": title or default_title,
        "status": status,
        "detail": detail,
    }
    if instance:
        body["instance"] = instance
    if errors is not None:
        body["errors"] = errors
    return body


def problem_response(status: int, detail: str, *, title: str | None = None, slug: str | None = None,
                     instance: str | None = None, errors: list[dict[str, str]] | None = None,
                     headers: dict[str, str] | None = None) -> JSONResponse:
    """An RFC 9457 problem details response."""
    return JSONResponse(
        problem_body(status, detail, title=title, slug=slug, instance=instance, errors=errors),
        status_code=status, media_type=PROBLEM_JSON, headers=headers,
    )


class ProblemError(Exception):
    """Raise anywhere in a request to answer with a problem document."""

    def __init__(self, status: int, detail: str, *, title: str | None = None, slug: str | None = None,
                 errors: list[dict[str, str]] | None = None, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.title = title
        self.slug = slug
        self.errors = errors
        self.headers = headers


def not_found(what: str) -> ProblemError:
    """A 404 problem for a resource the caller may not see or that does not exist."""
    return ProblemError(404, f"{what} not found", slug="not-found")


def forbidden(detail: str) -> ProblemError:
    """A 403 problem: the caller's role may never do this."""
    return ProblemError(403, detail, slug="forbidden")


def conflict(detail: str, slug: str = "conflict") -> ProblemError:
    """A 409 problem: the request conflicts with the resource's state."""
    return ProblemError(409, detail, slug=slug)


def invalid(field: str, message: str, *, status: int = 422) -> ProblemError:
    """One invalid field (checks that need the settings or the database, so pydantic cannot do them)."""
    return ProblemError(status, f"{field}: {message}", title="Validation failed", slug="validation-error",
                        errors=[{"field": field, "message": message}])


def retry_after_headers(seconds: int) -> dict[str, str]:
    """The ``Retry-After`` header of a transient 503."""
    return {"Retry-After": str(seconds)}


def _retry_after(request: Request) -> dict[str, str]:
    settings = getattr(request.app.state, "settings", None)
    return retry_after_headers(getattr(settings, "retry_after_s", 1))


def _field_name(loc: tuple[Any, ...]) -> str:
    """("body", "gyro", 17, 2) -> "gyro[17][2]"; ("query", "leg") -> "leg"."""
    parts = list(loc[1:]) if loc and loc[0] in ("body", "query", "path", "header", "cookie") else list(loc)
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += ("." if out else "") + str(p)
    return out or (str(loc[0]) if loc else "request")


def validation_errors(exc: RequestValidationError) -> list[dict[str, str]]:
    """The pydantic errors of a request as the problem's ``errors`` list."""
    errs = exc.errors()
    # a JSON syntax error's location is ("body", <byte offset>): the field is the body itself
    out = [{"field": "body" if e.get("type") == "json_invalid" else _field_name(tuple(e.get("loc", ()))),
            "message": str(e.get("msg", "invalid"))}
           for e in errs[:MAX_FIELD_ERRORS]]
    if len(errs) > MAX_FIELD_ERRORS:
        out.append({"field": "", "message": f"... and {len(errs) - MAX_FIELD_ERRORS} more errors"})
    return out


async def _problem_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ProblemError)
    return problem_response(exc.status, exc.detail, title=exc.title, slug=exc.slug, instance=request.url.path,
                            errors=exc.errors, headers=exc.headers)


async def _validation_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = validation_errors(exc)
    first = errors[0] if errors else {"field": "request", "message": "invalid"}
    detail = f"{first['field']}: {first['message']}"
    if len(errors) > 1:
        detail += f" (and {len(exc.errors()) - 1} more)"
    log.info("%s %s -> 422 %s", request.method, request.url.path, detail[:300])
    return problem_response(422, detail, title="Validation failed", slug="validation-error",
                            instance=request.url.path, errors=errors)


# The HTML error page for a request to a web page (status, problem detail), or None for an API request.
PageErrors = Callable[[Request, int, str], Response | None]


async def _http_exception_handler(request: Request, exc: Exception, page_errors: PageErrors | None = None
                                  ) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    status = exc.status_code
    detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(status).phrase
    page = page_errors(request, status, detail) if page_errors is not None else None
    if page is not None:
        page.headers.update(exc.headers or {})  # Allow on a 405
        return page
    if status == 404 and detail == "Not Found":
        detail = f"No resource at {request.url.path}"
    elif status == 405:
        detail = f"Method {request.method} is not allowed on {request.url.path}"
    return problem_response(status, detail, instance=request.url.path, headers=dict(exc.headers or {}))


async def _pool_timeout_handler(request: Request, exc: Exception) -> JSONResponse:
    # Every pooled connection stayed busy for the pool timeout: tell the client to come back, do not queue.
    log.warning("%s %s -> 503: no database connection free (%s)", request.method, request.url.path, exc)
    return problem_response(503, "The service is busy; retry after the time in Retry-After", title="Busy",
                            slug="overloaded", instance=request.url.path, headers=_retry_after(request))


async def _operational_handler(request: Request, exc: Exception) -> JSONResponse:
    # Unreachable server, dropped connection, SQLite write lock held past its busy timeout: all transient.
    log.warning("%s %s -> 503: database unavailable: %s", request.method, request.url.path,
                " ".join(str(getattr(exc, "orig", exc)).split())[:200])
    return problem_response(503, "The database is unavailable or busy; retry after the time in Retry-After",
                            title="Database unavailable", slug="database-unavailable", instance=request.url.path,
                            headers=_retry_after(request))


async def _unhandled_handler(request: Request, exc: Exception) -> JSONResponse:
    # The traceback goes to the log only; the client gets a generic problem document.
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return problem_response(500, "An internal error occurred; it has been logged.", slug="internal-error",
                            instance=request.url.path)


def install_error_handlers(app: FastAPI, page_errors: PageErrors | None = None) -> None:
    """Turn every error, including unexpected ones, into a problem details response; ``page_errors`` renders an
    unknown address or a wrong method under the web pages as a page instead."""
    app.add_exception_handler(ProblemError, _problem_error_handler)
    app.add_exception_handler(RequestValidationError, _validation_handler)
    app.add_exception_handler(StarletteHTTPException, partial(_http_exception_handler, page_errors=page_errors))
    app.add_exception_handler(PoolTimeoutError, _pool_timeout_handler)
    app.add_exception_handler(OperationalError, _operational_handler)
    app.add_exception_handler(Exception, _unhandled_handler)
