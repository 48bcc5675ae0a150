"""Request and response bodies of the HTTP API v1 (pydantic v2). Field names follow the contract."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, field_validator, model_validator

Leg = Literal["left", "right"]
Segment = Literal["thigh", "shank"]
Activity = Literal["walking", "running", "unknown"]
GyroUnit = Literal["deg/s", "rad/s"]
AccUnit = Literal["m/s2", "g"]
Role = Literal["admin", "clinician", "device"]
SessionStatus = Literal["receiving", "queued", "processing", "done", "failed"]

# NaN and infinities are rejected explicitly: Python's json module parses the NaN/Infinity literals.
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Xyz = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
Name = Annotated[str, Field(min_length=1, max_length=200)]


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ---------------------------------------------------------------- who am I, clinicians, tokens

class MeOut(BaseModel):
    token_id: str
    role: Role
    name: str | None
    clinician_id: str | None
    patient_id: str | None


class ClinicianIn(_In):
    name: Name
    email: Annotated[str, Field(max_length=320, pattern=r"^[^@\s]+@[^@\s]+$")] | None = None


class ClinicianOut(BaseModel):
    id: str
    name: str
    email: str | None
    created_at: datetime


class ClinicianCreated(ClinicianOut):
    token: str = Field(description="Bearer token of the clinician; shown once.")
    token_id: str


class TokenOut(BaseModel):
    id: str
    role: Role
    name: str | None
    clinician_id: str | None
    patient_id: str | None
    created_at: datetime
    revoked_at: datetime | None


class DeviceTokenIn(_In):
    name: Annotated[str, Field(max_length=200)] | None = Field(None, description="e.g. the device's model")


class DeviceTokenCreated(BaseModel):
    token: str = Field(description="Bearer token for the patient's app; shown once.")
    token_id: str
    patient_id: str
    name: str | None


# ---------------------------------------------------------------- patients

class PatientIn(_In):
    external_id: Annotated[str, Field(max_length=200)] | None = None
    display_name: Annotated[str, Field(max_length=200)] | None = None
    affected_leg: Leg | None = None
    timezone: Annotated[str, Field(max_length=64)] = "UTC"
    clinician_id: str | None = Field(None, description="Admin only: the clinician who owns the patient.")

    @field_validator("timezone")
    @classmethod
    def _known_timezone(cls, value: str) -> str:
        try:
            ZoneInfo(value)
        except (ZoneInfoNotFoundError, ValueError) as exc:
            raise ValueError(f"unknown IANA time zone {value!r}") from exc
        return value


class PatientPatch(_In):
    """Fields to change; fields left out stay as they are (null clears an optional field)."""

    external_id: Annotated[str, Field(max_length=200)] | None = None
    display_name: Annotated[str, Field(max_length=200)] | None = None
    affected_leg: Leg | None = None
    timezone: Annotated[str, Field(max_length=64)] | None = None

    @field_validator("timezone")
    @classmethod
    def _known_timezone(cls, value: str | None) -> str:
        if value is None:
            raise ValueError("timezone cannot be null")
        return PatientIn._known_timezone(value)


class PatientOut(BaseModel):
    id: str
    clinician_id: str | None
    external_id: str | None
    display_name: str | None
    affected_leg: Leg | None
    timezone: str
    created_at: datetime


class PatientPage(BaseModel):
    items: list[PatientOut]
    next_cursor: str | None


# ---------------------------------------------------------------- sessions

class SensorIn(_In):
    sensor_id: Annotated[str, Field(min_length=1, max_length=64)]
    leg: Leg
    segment: Segment
    sample_rate_hz: Annotated[float, Field(ge=1, le=2000, allow_inf_nan=False)]
    gyro_unit: GyroUnit = "deg/s"
    acc_unit: AccUnit = "m/s2"


class SessionIn(_In):
    patient_id: str
    client_session_id: Annotated[str, Field(min_length=1, max_length=200)]
    started_at: AwareDatetime
    activity: Activity = "walking"
    sensors: Annotated[list[SensorIn], Field(min_length=1, max_length=16)]

    @model_validator(mode="after")
    def _unique_sensors(self) -> SessionIn:
        ids = [s.sensor_id for s in self.sensors]
        if len(set(ids)) != len(ids):
            raise ValueError("sensor_id values must be unique within a session")
        places = [(s.leg, s.segment) for s in self.sensors]
        if len(set(places)) != len(places):
            raise ValueError("at most one sensor per leg and segment")
        return self


class SensorOut(BaseModel):
    sensor_id: str
    leg: Leg
    segment: Segment
    sample_rate_hz: float
    gyro_unit: GyroUnit
    acc_unit: AccUnit


class ReceivedOut(BaseModel):
    batches: int
    samples: int
    gaps: int = Field(description="Detected gaps: missing seq numbers or time jumps > 1.5 sample periods")
    gap_s: float = Field(description="Total time missing inside gaps, seconds")
    first_t_s: float | None
    last_t_s: float | None
    missing_seq: list[int] = Field(description="Missing seq numbers between the lowest and highest received "
                                               "(at most 100 listed)")
    observed_rate_hz: float | None = Field(description="Sample rate implied by the timestamps (median step)")


class SessionOut(BaseModel):
    id: str
    patient_id: str
    client_session_id: str
    started_at: datetime
    activity: Activity
    status: SessionStatus
    error: str | None
    sensors: list[SensorOut]
    received: dict[str, ReceivedOut]
    summary: dict[str, Any] | None
    algorithm_version: str | None
    created_at: datetime
    completed_at: datetime | None
    processed_at: datetime | None
    attempts: int


class SessionListItem(BaseModel):
    id: str
    patient_id: str
    client_session_id: str
    started_at: datetime
    activity: Activity
    status: SessionStatus
    algorithm_version: str | None
    summary: dict[str, Any] | None


class SessionPage(BaseModel):
    items: list[SessionListItem]
    next_cursor: str | None


class BatchIn(_In):
    sensor_id: Annotated[str, Field(min_length=1, max_length=64)]
    seq: Annotated[int, Field(ge=0, le=2**31 - 1)]
    t0_ms: FiniteFloat
    gyro: list[Xyz]
    acc: list[Xyz]
    timestamps_ms: list[FiniteFloat] | None = None

    @model_validator(mode="after")
    def _same_lengths(self) -> BatchIn:
        if len(self.gyro) != len(self.acc):
            raise ValueError(f"gyro has {len(self.gyro)} rows but acc has {len(self.acc)}")
        if self.timestamps_ms is not None and len(self.timestamps_ms) != len(self.gyro):
            raise ValueError(f"timestamps_ms has {len(self.timestamps_ms)} values but gyro has {len(self.gyro)} rows")
        if not self.gyro:
            raise ValueError("a batch needs at least one sample")
        return self


class BatchOut(BaseModel):
    sensor_id: str
    seq: int
    samples: int
    duplicate: bool = Field(description="true when this was an identical replay of a stored batch (HTTP 200)")


# ---------------------------------------------------------------- results

class StrideOut(BaseModel):
    leg: Leg
    index: int
    started_at: datetime
    t_start_s: float
    t_end_s: float
    duration_s: float | None
    t_toe_off_s: float | None
    stance_time_s: float | None
    swing_time_s: float | None
    stance_pct: float | None
    peak_swing_flexion_deg: float | None
    min_flexion_deg: float | None
    rom_deg: float | None
    stance_flexion_deg: float | None
    estimator: str
    quality: float | None
    quality_reasons: list[str]


class StridesOut(BaseModel):
    session_id: str
    strides: list[StrideOut]


class KneeAngleOut(BaseModel):
    session_id: str
    leg: Leg
    fs_hz: float = Field(description="Sample rate of the full-resolution trace")
    n_total: int = Field(description="Samples of the full trace inside the requested window")
    downsampling: Literal["none", "minmax"]
    t_s: list[float]
    angle_deg: list[float | None]
    estimator: list[str | None]
