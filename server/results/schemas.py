"""Bodies of the result endpoints. The stride fields come from :mod:`server.results.stride_record`."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from pipeline.reasons import REASONS
from server.enums import Leg, StrideActivity
from server.results.stride_record import STRIDE_UNITS
from server.schema_types import OrmOut, UtcDatetime

# A stored stride always has its two heel strikes; any other value may be missing.
_ALWAYS_PRESENT = frozenset({"t_start_s", "t_end_s"})


def _value_field(name: str) -> tuple[Any, Any]:
    kind: Any = float if name in _ALWAYS_PRESENT else float | None
    return kind, Field(..., description=f"unit: {STRIDE_UNITS[name]}")


StrideOut = create_model(
    "StrideOut",
    __doc__="One stride of one leg: its values (units in the names) and where its angle came from.",
    leg=(Leg, ...),
    index=(int, ...),
    started_at=(UtcDatetime, ...),
    __base__=OrmOut,
    **{name: _value_field(name) for name in STRIDE_UNITS},
    estimator=(str, ...),
    quality=(float | None, ...),
    quality_reasons=(list[str], Field(..., description="why the quality is below 1; codes: " + "; ".join(
        f"`{code}`: {meaning}" for code, meaning in REASONS.items()))),
    activity=(StrideActivity, Field(..., description="what the stride was processed as; trends never pool them")),
    fallback=(bool, Field(..., description="the angle came from the fallback of the activity's primary estimator")),
)


class StridesOut(BaseModel):
    """The strides of a processed session."""

    session_id: str
    strides: list[StrideOut]


class KneeAngleOut(BaseModel):
    """The continuous knee flexion of one leg, possibly down-sampled."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "session_id": "3f0c2a9e8b7d4c1a9e6f5d4c3b2a1908", "leg": "left", "fs_hz": 100.0, "n_total": 6000,
        "downsampling": "minmax", "t_s": [0.0, 0.41, 0.83], "angle_deg": [4.2, 61.8, None],
        "estimator": ["go", "go", None]}]})

    session_id: str
    leg: Leg
    fs_hz: float = Field(description="Sample rate of the full-resolution trace")
    n_total: int = Field(description="Samples of the full trace inside the requested window")
    downsampling: Literal["none", "minmax"]
    t_s: list[float]
    angle_deg: list[float | None]
    estimator: list[str | None]
    withheld: str | None = Field(
        None, description="Why every angle of this leg is null, when it is: `no_gait` = the session has no gait "
                          "stride on this leg to learn the knee axes and the angle's zero from (exercises or sitting "
                          "alone), so no angle is shown rather than a wrong one")
    not_worn_s: list[tuple[float, float]] = Field(
        default_factory=list, description="Time spans [s] in which this leg's sensors were not on the leg (at rest "
                                          "in a posture other than standing while the other leg walked: taken off, "
                                          "left lying somewhere): their angles are null")


class MetricSummary(BaseModel):
    """A stride metric's summary over one estimator's strides."""

    mean: float | None
    median: float | None
    sd: float | None


class EstimatorSummary(BaseModel):
    """One estimator's strides on one leg."""

    n_strides: int
    peak_swing_flexion_deg: MetricSummary
    rom_deg: MetricSummary
    min_flexion_deg: MetricSummary
    stride_estimators: dict[str, int] = Field(description="Strides per estimator that produced them (auto mixes)")


class PairDifference(BaseModel):
    """How far two estimators' continuous angle traces are apart."""

    a: str
    b: str
    rms_deg: float | None = Field(description="RMS of the sample-wise difference of the two angle traces")
    mean_deg: float | None = Field(description="Mean of a - b: the part of the difference that is an offset")
    n_samples: int


class LegComparison(BaseModel):
    """Every estimator on one leg."""

    estimators: dict[str, EstimatorSummary]
    pairs: list[PairDifference]


class CompareOut(BaseModel):
    """Every knee estimator side by side on one session."""

    session_id: str
    activity: str
    algorithm_version: str
    estimators: list[str]
    failed: dict[str, str] = Field(description="Estimators that could not run on this session, with the reason")
    legs: dict[str, LegComparison]
    warnings: list[str]
