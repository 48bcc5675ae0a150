"""Bodies of the identity, clinician and token endpoints."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from server.enums import Role
from server.schema_types import Name, OrmOut, StrictIn, UtcDatetime


class MeOut(BaseModel):
    """Who the bearer token belongs to."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"token_id": "9e8d7c6b5a4f4e3d2c1b0a9f8e7d6c5b", "role": "clinician", "name": "Dr Ada Weber",
         "clinician_id": "5b2e9f1c3a4d4e6f8a7b9c0d1e2f3a4b", "patient_id": None}]})

    token_id: str
    role: Role
    name: str | None
    clinician_id: str | None
    patient_id: str | None


class ClinicianIn(StrictIn):
    """A new clinician."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"name": "Dr Ada Weber", "email": "ada.weber@clinic.example"}]})

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

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"id": "5b2e9f1c3a4d4e6f8a7b9c0d1e2f3a4b", "name": "Dr Ada Weber", "email": "ada.weber@clinic.example",
         "created_at": "2026-11-20T08:00:00Z", "token": "gm_4q...", "token_id": "9e8d7c6b5a4f4e3d2c1b0a9f8e7d6c5b"}]})

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

    model_config = ConfigDict(json_schema_extra={"examples": [{"name": "Pixel 8 of patient 42"}]})

    name: Annotated[str, Field(max_length=200)] | None = Field(None, description="e.g. the device's model")


class DeviceTokenCreated(BaseModel):
    """A new device token, shown once."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"token": "gm_Zx...", "token_id": "9e8d7c6b5a4f4e3d2c1b0a9f8e7d6c5b",
         "patient_id": "8c1d0c6f2b7e4a5f9d3e2a1b0c9d8e7f", "name": "Pixel 8 of patient 42"}]})

    token: str = Field(description="Bearer token for the patient's app; shown once.")
    token_id: str
    patient_id: str
    name: str | None
