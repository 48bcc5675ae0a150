"""Typed, immutable views of the API's JSON responses (unknown fields are ignored: the API only adds fields)."""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict

if TYPE_CHECKING:
    import pandas


def _pandas() -> Any:  # noqa: ANN401 - the module
    try:
        import pandas
    except ImportError as exc:
        raise ImportError("to_dataframe() needs pandas: pip install 'gaitmon[dataframe]' (or pandas)") from exc
    return pandas


class ApiModel(BaseModel):
    """Base of every response type: frozen, and unknown fields ignored so a newer server does not break this client."""

    model_config = ConfigDict(frozen=True, extra="ignore")


class Me(ApiModel):
    """Who the token belongs to (``GET /v1/me``)."""

    token_id: str
    role: str
    name: str | None = None
    clinician_id: str | None = None
    patient_id: str | None = None


class ClinicianCreated(ApiModel):
    """A new clinician with its token (shown once)."""

    id: str
    name: str
    email: str | None = None
    created_at: datetime
    token: str
    token_id: str


class Patient(ApiModel):
    """A patient as the API returns it."""

    id: str
    clinician_id: str | None = None
    external_id: str | None = None
    display_name: str | None = None
    affected_leg: str | None = None
    timezone: str = "UTC"
    created_at: datetime


class DeviceToken(ApiModel):
    """A device enrolment token bound to one patient (shown once)."""

    token: str
    token_id: str
    patient_id: str
    name: str | None = None


class Sensor(ApiModel):
    """One declared IMU of a session."""

    sensor_id: str
    leg: str
    segment: str
    sample_rate_hz: float
    gyro_unit: str = "deg/s"
    acc_unit: str = "m/s2"


class Received(ApiModel):
    """What the server holds of one sensor: batches, samples, gaps."""

    batches: int
    samples: int
    gaps: int
    gap_s: float
    first_t_s: float | None = None
    last_t_s: float | None = None
    missing_seq: tuple[int, ...] = ()
    observed_rate_hz: float | None = None


class Session(ApiModel):
    """A recording session with its status, what was received and, once processed, its summary."""

    id: str
    patient_id: str
    client_session_id: str
    started_at: datetime
    activity: str
    status: str
    error: str | None = None
    sensors: tuple[Sensor, ...] = ()
    received: dict[str, Received] = {}
    summary: dict[str, Any] | None = None
    algorithm_version: str | None = None
    created_at: datetime
    completed_at: datetime | None = None
    processed_at: datetime | None = None
    attempts: int = 0

    @property
    def finished(self) -> bool:
        """Processing is over (``done`` or ``failed``)."""
        return self.status in ("done", "failed")


class BatchResult(ApiModel):
    """The answer to one batch upload; ``duplicate`` when the server already held it."""

    sensor_id: str
    seq: int
    samples: int
    duplicate: bool


class Stride(ApiModel):
    """One stride of one leg: timing, knee angles, estimator and quality."""

    leg: str
    index: int
    started_at: datetime
    t_start_s: float
    t_end_s: float
    duration_s: float | None = None
    t_toe_off_s: float | None = None
    stance_time_s: float | None = None
    swing_time_s: float | None = None
    stance_pct: float | None = None
    peak_swing_flexion_deg: float | None = None
    min_flexion_deg: float | None = None
    rom_deg: float | None = None
    stance_flexion_deg: float | None = None
    estimator: str
    quality: float | None = None
    quality_reasons: tuple[str, ...] = ()


class Strides(ApiModel):
    """The strides of one session."""

    session_id: str
    strides: tuple[Stride, ...]

    def to_dataframe(self) -> pandas.DataFrame:
        """One row per stride, the columns of :class:`Stride` (needs pandas)."""
        pd = _pandas()
        return pd.DataFrame([s.model_dump() for s in self.strides], columns=list(Stride.model_fields))


class TrendBucket(ApiModel):
    """One day or week of a trend."""

    start: datetime
    end: datetime
    n_sessions: int
    n_strides: int
    n_excluded: int = 0
    mean: float | None = None
    sd: float | None = None
    median: float | None = None
    p10: float | None = None
    p90: float | None = None
    cv: float | None = None
    n_values: int = 0


class TrendSlope(ApiModel):
    """Slope per week of a trend, with its 95 % CI."""

    slope_per_week: float | None = None
    ci95: tuple[float | None, float | None] = (None, None)
    n: int = 0
    method: str
    p_value: float | None = None
    basis: str | None = None


class TrendChange(ApiModel):
    """Latest against baseline window, and whether the change exceeds the minimal detectable change."""

    baseline: float | None = None
    latest: float | None = None
    delta: float | None = None
    mdc: float | None = None
    significant: bool = False
    direction: str | None = None
    window_days: float | None = None
    reasons: tuple[str, ...] = ()


class Trends(ApiModel):
    """A patient's trend of one metric and leg."""

    patient_id: str
    metric: str
    unit: str
    leg: str | None = None
    bucket: str
    timezone: str
    buckets: tuple[TrendBucket, ...]
    trend: TrendSlope
    change: TrendChange
    excluded: dict[str, int] = {}
    rules: dict[str, Any] = {}

    def to_dataframe(self) -> pandas.DataFrame:
        """One row per bucket (start, end, n_sessions, n_strides, mean, sd, median, ...; needs pandas)."""
        pd = _pandas()
        return pd.DataFrame([b.model_dump() for b in self.buckets], columns=list(TrendBucket.model_fields))
