"""The error the client raises for every answer that is not a success: the server's RFC 9457 problem details."""

from __future__ import annotations

from dataclasses import dataclass, field
from http import HTTPStatus

import httpx


@dataclass(frozen=True)
class FieldError:
    """One invalid field of a 422 (``gyro[17][2]``, ``started_at``, ...)."""

    field: str
    message: str


# Not frozen: the interpreter and pytest set attributes (__notes__, __traceback__) on exceptions.
@dataclass(eq=False)
class ApiError(Exception):
    """An error response: ``status``, ``title``, ``detail`` and the per-field ``errors`` of a validation failure.

    ``type`` is the problem type URI (``urn:gaitmon:problem:<slug>``), ``retry_after_s`` is set on a 429/503 that
    the client gave up retrying, ``request_id`` is the server's ``X-Request-ID`` (quote it when asking for help).
    """

    status: int
    title: str
    detail: str
    errors: tuple[FieldError, ...] = ()
    type: str | None = None
    instance: str | None = None
    retry_after_s: float | None = None
    request_id: str | None = field(default=None, compare=False)

    def __str__(self) -> str:
        rid = f" [request {self.request_id}]" if self.request_id else ""
        return f"HTTP {self.status} {self.title}: {self.detail}{rid}"

    @classmethod
    def from_response(cls, resp: httpx.Response, retry_after_s: float | None = None) -> ApiError:
        """Read a problem document; any other body becomes the detail (shortened), the reason phrase the title."""
        try:
            phrase = HTTPStatus(resp.status_code).phrase
        except ValueError:
            phrase = "Error"
        body: object = None
        if "json" in resp.headers.get("content-type", ""):
            try:
                body = resp.json()
            except ValueError:
                body = None
        rid = resp.headers.get("x-request-id")
        if isinstance(body, dict):
            raw_errors = body.get("errors") or []
            errors = tuple(FieldError(str(e.get("field", "")), str(e.get("message", "")))
                           for e in raw_errors if isinstance(e, dict))
            return cls(status=resp.status_code, title=str(body.get("title") or phrase),
                       detail=str(body.get("detail") or ""), errors=errors, type=body.get("type"),
                       instance=body.get("instance"), retry_after_s=retry_after_s, request_id=rid)
        return cls(status=resp.status_code, title=phrase, detail=resp.text[:500], retry_after_s=retry_after_s,
                   request_id=rid)
