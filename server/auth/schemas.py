"""Bodies of the identity, clinician and token endpoints."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, Field

from server.enums import Role
from server.schema_types import Name, OrmOut, StrictIn, UtcDatetime


class MeOut(BaseModel):
    """Who the bearer token belongs to."""

    token_id: str
    role: Role
    name: str | None
    clinician_id: str | None
    patient_id: str | None


class ClinicianIn(StrictIn):
    """A new clinician."""

    name: Name
    email: Annotated[str, Field(max_length=320, pattern=r"^[^@\s]+@[^@\s]+$")] | None = None


class ClinicianOut(OrmOut):
    """A clinician."""

    id: str
    name: str
    email: str | None
    created_at: UtcDatetime


class ClinicianCreated(ClinicianOut):
    """A new clinician with the bearer token issued for them."""

    token: str = Field(description="Bearer token of the clinician; shown once.")
    token_id: str


class TokenOut(OrmOut):
    """A token's metadata (never the token itself)."""

    id: str
    role: Role
    name: str | None
    clinician_id: str | None
    patient_id: str | None
    created_at: UtcDatetime
    revoked_at: UtcDatetime | None


class DeviceTokenIn(StrictIn):
    """A new device token for a patient's app."""

    name: Annotated[str, Field(max_length=200)] | None = Field(None, description="e.g. the device's model")


class DeviceTokenCreated(BaseModel):
    """A new device token, shown once."""

    token: str = Field(description="Bearer token for the patient's app; shown once.")
    token_id: str
    patient_id: str
    name: str | None
