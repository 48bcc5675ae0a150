"""Response bodies of the trend endpoints, for the OpenAPI document.

The routes hand back the service's plain JSON documents directly (FastAPI's encoder would walk a year of buckets
field by field, which costs more than computing them); these models declare their shape. ``extra="allow"``: the
nested documents carry more fields than named here, every one of them a JSON type.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from server.enums import StrideActivity


class _Doc(BaseModel):
    model_config = ConfigDict(extra="allow")


class BucketOut(_Doc):
    """The pooled included strides of one day or week."""

    start: str
    end: str
    n_sessions: int
    n_strides: int
    n_excluded: int
    mean: float | None
    sd: float | None
    median: float | None
    p10: float | None
    p90: float | None


class TrendLineOut(_Doc):
    """Slope per week over session-level (count metrics: day-level) values."""

    slope_per_week: float | None
    ci95: list[float | None]
    n: int
    method: str


class ChangeOut(_Doc):
    """Baseline vs latest window."""

    baseline: float | None
    latest: float | None
    delta: float | None
    mdc: float | None
    significant: bool
    direction: str | None


class TrendsOut(_Doc):
    """Longitudinal trend of one metric of one leg and activity."""

    model_config = ConfigDict(extra="allow", json_schema_extra={"examples": [{
        "patient_id": "8c1d0c6f2b7e4a5f9d3e2a1b0c9d8e7f", "metric": "peak_swing_flexion_deg", "unit": "deg",
        "leg": "left", "bucket": "week", "activity": "walking", "timezone": "Europe/Berlin",
        "from": "2026-10-31T23:00:00+00:00", "to": "2026-11-15T23:00:00+00:00",
        "buckets": [{"start": "2026-11-02T00:00:00+01:00", "end": "2026-11-09T00:00:00+01:00", "n_sessions": 3,
                     "n_strides": 60, "n_excluded": 0, "mean": 57.0, "sd": 1.6468, "median": 57.0, "p10": 55.0,
                     "p90": 59.0, "cv": 0.0289, "n_values": 60}],
        "trend": {"slope_per_week": 4.666667, "ci95": [4.666667, 4.666667], "n": 3, "method": "ols", "p_value": 0.0,
                  "basis": "sessions"},
        "change": {"baseline": 55.0, "latest": 59.0, "delta": 4.0, "mdc": 5.0, "significant": False,
                   "direction": "unchanged", "window_days": 14.0, "reasons": ["|delta| 4 <= MDC 5"]},
        "excluded": {"n_low_quality": 0, "n_implausible": 0},
        "rules": {"min_quality": 0.5, "plausible_range": [0.0, 140.0], "min_strides_per_session": 5,
                  "trend_points": "per session", "better": "higher"}}]})

    patient_id: str
    metric: str
    unit: str
    leg: str | None
    bucket: str
    activity: StrideActivity
    timezone: str
    buckets: list[BucketOut]
    trend: TrendLineOut
    change: ChangeOut
    excluded: dict[str, int]
    rules: dict[str, Any]


class SymmetryOut(_Doc):
    """Affected vs other leg per bucket."""

    patient_id: str
    metric: str
    unit: str
    bucket: str
    activity: StrideActivity
    affected_leg: str | None
    reference_leg: str
    other_leg: str
    timezone: str
    buckets: list[dict[str, Any]]


class CompletenessOut(_Doc):
    """Days with data, strides and minutes of one activity per local day."""

    patient_id: str
    activity: StrideActivity
    timezone: str
    days: int
    days_with_data: int
    days_with_sessions: int
    strides_total: int
    walking_min_total: float
    last_upload_at: str | None
    last_session_at: str | None
    per_day: list[dict[str, Any]]


class AttentionOut(_Doc):
    """Flagged patients, most severe first, one page at a time."""

    items: list[dict[str, Any]] = Field(description="{patient, severity, flags: [{kind, severity, reason, ...}]}")
    next_cursor: str | None
    n_flagged: int
    n_patients: int
    generated_at: str
    params: dict[str, Any]
    rules: dict[str, Any] = Field(description="what each flag means, its method and the thresholds used")


class FhirBundleOut(_Doc):
    """A FHIR R4 Bundle (type collection) of daily Observations."""

    resourceType: str  # noqa: N815 - FHIR's field name
    id: str
    type: str
    timestamp: str
    entry: list[dict[str, Any]]
