"""Field types the bodies share: strict requests, finite floats, 3-vectors, names, UTC times, ORM responses."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from server.utc import as_utc

# NaN and infinities are rejected explicitly: Python's json module parses the NaN/Infinity literals.
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Xyz = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
Name = Annotated[str, Field(min_length=1, max_length=200)]


class StrictIn(BaseModel):
    """A request body: unknown fields are an error, not silently ignored."""

    model_config = ConfigDict(extra="forbid")


def _utc(value: datetime) -> datetime:
    return as_utc(value)


# Stored times are UTC; SQLite hands them back naive, so every response says so.
UtcDatetime = Annotated[datetime, AfterValidator(_utc)]


class OrmOut(BaseModel):
    """A response body read from an ORM row's attributes."""

    model_config = ConfigDict(from_attributes=True)
