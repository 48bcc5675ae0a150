"""Bodies of the patient endpoints."""

from __future__ import annotations

from typing import Annotated
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pydantic import BaseModel, ConfigDict, Field, field_validator

from server.enums import Leg
from server.schema_types import FiniteFloat, OrmOut, StrictIn, UtcDatetime


def known_timezone(value: str) -> str:
    """The IANA time zone name, or a validation error."""
    try:
        ZoneInfo(value)
    except (ZoneInfoNotFoundError, ValueError, OSError) as exc:  # OSError: a folder of the database ("Europe")
        raise ValueError(f"unknown IANA time zone {value!r}") from exc
    return value


class PatientIn(StrictIn):
    """A new patient."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"external_id": "MRN-0042", "display_name": "Patient 42", "affected_leg": "left",
         "timezone": "Europe/Berlin"}]})

    external_id: Annotated[str, Field(max_length=200)] | None = None
    display_name: Annotated[str, Field(max_length=200)] | None = None
    affected_leg: Leg | None = None
    timezone: Annotated[str, Field(max_length=64)] = "UTC"
    prescribed_sessions_per_week: Annotated[FiniteFloat, Field(gt=0, le=28)] | None = None
    clinician_id: str | None = Field(None, description="Admin only: the clinician who owns the patient.")

    @field_validator("timezone")
    @classmethod
    def _known_timezone(cls, value: str) -> str:
        return known_timezone(value)


class PatientPatch(StrictIn):
    """Fields to change; fields left out stay as they are (null clears an optional field)."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"affected_leg": "right"}, {"display_name": None}]})

    external_id: Annotated[str, Field(max_length=200)] | None = None
    display_name: Annotated[str, Field(max_length=200)] | None = None
    affected_leg: Leg | None = None
    timezone: Annotated[str, Field(max_length=64)] | None = None
    prescribed_sessions_per_week: Annotated[FiniteFloat, Field(gt=0, le=28)] | None = None

    @field_validator("timezone")
    @classmethod
    def _known_timezone(cls, value: str | None) -> str:
        if value is None:
            raise ValueError("timezone cannot be null")
        return known_timezone(value)


class PatientOut(OrmOut):
    """A patient."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"id": "8c1d0c6f2b7e4a5f9d3e2a1b0c9d8e7f", "clinician_id": "5b2e9f1c3a4d4e6f8a7b9c0d1e2f3a4b",
         "external_id": "MRN-0042", "display_name": "Patient 42", "affected_leg": "left", "timezone": "Europe/Berlin",
         "created_at": "2026-11-20T08:05:00Z"}]})

    id: str
    clinician_id: str | None
    external_id: str | None
    display_name: str | None
    affected_leg: Leg | None
    timezone: str
    prescribed_sessions_per_week: float | None = None
    created_at: UtcDatetime


class PatientPage(BaseModel):
    """One page of patients and the cursor of the next."""

    items: list[PatientOut]
    next_cursor: str | None
