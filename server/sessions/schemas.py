"""Bodies of the session, upload and processing-summary endpoints."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from pipeline.params import WALKING
from server.calibrations.schemas import CalibrationUsed
from server.enums import AccUnit, Activity, GyroUnit, Leg, Segment, SessionStatus
from server.schema_types import FiniteFloat, OrmOut, SafeStr, StartedAt, StrictIn, StrictInt, UtcDatetime, Xyz


class SensorIn(StrictIn):
    """One sensor of a new session."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"sensor_id": "L-thigh", "leg": "left", "segment": "thigh", "sample_rate_hz": 100.0, "gyro_unit": "deg/s",
         "acc_unit": "m/s2"}]})

    sensor_id: Annotated[SafeStr, Field(min_length=1, max_length=64)]
    leg: Leg
    segment: Segment
    sample_rate_hz: Annotated[FiniteFloat, Field(ge=1, le=2000)]
    gyro_unit: GyroUnit = GyroUnit.deg_s
    acc_unit: AccUnit = AccUnit.m_s2


class SessionIn(StrictIn):
    """A new recording session with its sensors."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "patient_id": "8c1d0c6f2b7e4a5f9d3e2a1b0c9d8e7f", "client_session_id": "721c30b8-cba4-552c-8244-4ddd3cc3bc67",
        "started_at": "2026-11-21T09:30:00+01:00", "activity": "walking",
        "sensors": [{"sensor_id": "L-thigh", "leg": "left", "segment": "thigh", "sample_rate_hz": 100.0},
                     {"sensor_id": "L-shank", "leg": "left", "segment": "shank", "sample_rate_hz": 100.0}]}]})

    patient_id: SafeStr
    client_session_id: Annotated[SafeStr, Field(min_length=1, max_length=200)]
    started_at: StartedAt
    activity: Activity = Activity.walking
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


class SensorOut(OrmOut):
    """A sensor of a session."""

    sensor_id: str
    leg: Leg
    segment: Segment
    sample_rate_hz: float
    gyro_unit: GyroUnit
    acc_unit: AccUnit


class ReceivedOut(BaseModel):
    """What arrived of one sensor."""

    batches: int
    samples: int
    gaps: int = Field(description="Detected gaps: missing seq numbers or time jumps > "
                                  f"{WALKING.prepare.gap_factor:g} sample periods (the pipeline's gap rule)")
    gap_s: float = Field(description="Total time missing inside gaps, seconds")
    first_t_s: float | None
    last_t_s: float | None
    missing_seq: list[int] = Field(description="Missing seq numbers between the lowest and highest received "
                                               "(at most 100 listed)")
    observed_rate_hz: float | None = Field(description="Sample rate implied by the timestamps (median step)")


class LegSummaryOut(BaseModel):
    """The processing summary of one leg (:meth:`pipeline.types.SessionResult.summary`)."""

    model_config = ConfigDict(extra="allow")

    n_strides: int
    walking_s: float | None = None
    peak_swing_flexion_deg_median: float | None = None
    rom_deg_median: float | None = None
    estimators: dict[str, int] = Field(default_factory=dict)
    gaps: int = 0
    diagnostics: dict[str, Any] | None = Field(
        None, description="The pipeline's per-leg diagnostics (activity, axis fit residual, absolute reference, "
                          "shank clock lag, each sensor's accelerometer offset and gyro bias seen at rest and "
                          "removed, ...), when it reports them")


class SessionSummaryOut(BaseModel):
    """The processing summary stored with a session."""

    model_config = ConfigDict(extra="allow")

    algorithm_version: str | None = None
    activity: str | None = None
    warnings: list[str] = Field(default_factory=list)
    legs: dict[str, LegSummaryOut] = Field(default_factory=dict)
    calibration: dict[Leg, CalibrationUsed | None] | None = Field(
        None, description="Per leg of the session, the knee calibration it was processed with (the one valid at "
                          "the session's start), or null when the absolute level rests on the assumed standing "
                          "flexion; the leg's diagnostics say the same (level_source, calibration_id)")


class SessionOut(OrmOut):
    """A session with what it received and, once processed, its summary."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": "3f0c2a9e8b7d4c1a9e6f5d4c3b2a1908", "patient_id": "8c1d0c6f2b7e4a5f9d3e2a1b0c9d8e7f",
        "client_session_id": "721c30b8-cba4-552c-8244-4ddd3cc3bc67", "started_at": "2026-11-21T08:30:00Z",
        "activity": "walking", "status": "receiving", "error": None,
        "sensors": [{"sensor_id": "L-shank", "leg": "left", "segment": "shank", "sample_rate_hz": 100.0,
                     "gyro_unit": "deg/s", "acc_unit": "m/s2"}],
        "received": {"L-shank": {"batches": 12, "samples": 600, "gaps": 0, "gap_s": 0.0, "first_t_s": 0.003,
                                 "last_t_s": 5.993, "missing_seq": [], "observed_rate_hz": 100.0}},
        "summary": None, "algorithm_version": None, "created_at": "2026-11-21T08:30:01Z", "completed_at": None,
        "processed_at": None, "attempts": 0}]})

    id: str
    patient_id: str
    client_session_id: str
    started_at: UtcDatetime
    activity: Activity
    status: SessionStatus
    error: str | None
    sensors: list[SensorOut]
    received: dict[str, ReceivedOut]
    summary: SessionSummaryOut | None
    algorithm_version: str | None
    created_at: UtcDatetime
    completed_at: UtcDatetime | None
    processed_at: UtcDatetime | None
    attempts: int


class SessionListItem(OrmOut):
    """A session in a patient's list."""

    id: str
    patient_id: str
    client_session_id: str
    started_at: UtcDatetime
    activity: Activity
    status: SessionStatus
    algorithm_version: str | None
    summary: SessionSummaryOut | None


class SessionPage(BaseModel):
    """One page of sessions and the cursor of the next."""

    items: list[SessionListItem]
    next_cursor: str | None


class BatchIn(StrictIn):
    """One BLE batch of one sensor."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "sensor_id": "L-shank", "seq": 0, "t0_ms": 3.048,
        "gyro": [[-0.618, 1.411, 2.32], [-0.208, 1.58, 2.353], [-1.297, 1.237, 2.296]],
        "acc": [[9.1312, 2.6225, -2.3753], [9.0806, 2.6303, -2.4122], [9.1428, 2.6441, -2.4007]],
        "timestamps_ms": [3.048, 13.048, 23.048]}]})

    sensor_id: Annotated[SafeStr, Field(min_length=1, max_length=64)]
    seq: Annotated[StrictInt, Field(ge=0, le=2**31 - 1)]
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
    """The acknowledgement of a stored (or replayed) batch."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"sensor_id": "L-shank", "seq": 0, "samples": 3, "duplicate": False}]})

    sensor_id: str
    seq: int
    samples: int
    duplicate: bool = Field(description="true when this was an identical replay of a stored batch (HTTP 200)")
