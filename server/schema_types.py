"""Field types the bodies share: strict requests, finite floats, 3-vectors, names, UTC times, ORM responses."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, AwareDatetime, BaseModel, BeforeValidator, ConfigDict, Field, field_validator

from server.utc import as_utc, utcnow

# Largest finite float32: samples are stored as float32, a larger value would be stored as infinity.
FLOAT32_MAX = float(np.finfo(np.float32).max)
# The earliest recording start accepted, and how far after the server's clock a phone's clock may run ahead.
EARLIEST_STARTED_AT = datetime(2000, 1, 1, tzinfo=UTC)
STARTED_AT_FUTURE_SLACK = timedelta(days=1)


def text_problem(value: str) -> str | None:
    """Why ``value`` cannot be stored as text (a NUL, which PostgreSQL refuses, or a lone UTF-16 surrogate,
    which no UTF-8 database can hold), or None when it can."""
    if "\x00" in value:
        return "must not contain NUL characters"
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        return "must not contain unpaired surrogate characters"
    return None


def _storable_text(value: str) -> str:
    problem = text_problem(value)
    if problem is not None:
        raise ValueError(problem)
    return value


# Any text that reaches the database: path ids, names, external ids, cursors (query strings are checked as a
# whole by :mod:`server.request_hygiene`, string fields of request bodies by :class:`StrictIn`).
SafeStr = Annotated[str, AfterValidator(_storable_text)]

# NaN and infinities are rejected explicitly: Python's json module parses the NaN/Infinity literals. Strict: a
# boolean or a numeric string is not a number.
FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
# A sample value, stored as float32.
Float32 = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-FLOAT32_MAX, le=FLOAT32_MAX)]
StrictInt = Annotated[int, Field(strict=True)]
Xyz = Annotated[list[Float32], Field(min_length=3, max_length=3)]
Name = Annotated[SafeStr, Field(min_length=1, max_length=200)]


def _check_text_fields(value: Any) -> Any:
    if isinstance(value, str):
        _storable_text(value)
    elif isinstance(value, list | tuple) and value and isinstance(value[0], str):
        for item in value:
            if isinstance(item, str):
                _storable_text(item)
    return value


class StrictIn(BaseModel):
    """A request body: unknown fields are an error, not silently ignored; no text field may hold a NUL or a lone
    surrogate (checked on every string field, and on lists of strings, of every body)."""

    model_config = ConfigDict(extra="forbid")

    @field_validator("*", mode="after")
    @classmethod
    def _storable_strings(cls, value: Any) -> Any:
        return _check_text_fields(value)


def _utc(value: datetime) -> datetime:
    return as_utc(value)


# Stored times are UTC; SQLite hands them back naive, so every response says so.
UtcDatetime = Annotated[datetime, AfterValidator(_utc)]


def _rfc3339_string(value: Any) -> Any:
    # A number would be read as seconds since 1970: "started_at": 0 is a client bug, not a recording of 1970.
    if not isinstance(value, str | datetime):
        raise ValueError("must be an RFC 3339 date-time string with a UTC offset")
    return value


def _plausible_start(value: datetime) -> datetime:
    try:
        utc = value.astimezone(UTC)
    except OverflowError as exc:
        raise ValueError("is outside the range of representable instants") from exc
    latest = utcnow() + STARTED_AT_FUTURE_SLACK
    if not EARLIEST_STARTED_AT <= utc <= latest:
        raise ValueError(f"must be between {EARLIEST_STARTED_AT.isoformat()} and one day after the server's "
                         f"clock ({latest.isoformat(timespec='seconds')})")
    return utc


# An instant a client reports (a recording's start, a calibration's measurement): an RFC 3339 string with an offset,
# 2000-01-01T00:00Z .. server clock + 1 day, returned in UTC. Year 1 or 9999 would make every later date sum
# (a patient's local day, a trend bucket) overflow.
PlausibleInstant = Annotated[AwareDatetime, BeforeValidator(_rfc3339_string), AfterValidator(_plausible_start)]
StartedAt = PlausibleInstant


class OrmOut(BaseModel):
    """A response body read from an ORM row's attributes."""

    model_config = ConfigDict(from_attributes=True)
