"""Bodies of the knee calibration endpoints and the calibration block a processed session reports."""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, field_validator

from server.enums import CalibrationMethod, Leg
from server.schema_types import FiniteFloat, OrmOut, PlausibleInstant, StrictIn, UtcDatetime
from server.utc import utcnow

# Standing knee flexion a calibration may state, degrees (positive = flexion). Below 0 is hyperextension: genu
# recurvatum rarely exceeds 15-20 deg even in neurological patients. Above, a standing flexion contracture of
# 5-15 deg is common after knee surgery and crouch gait stands in up to ~45-60 deg; a knee that stands more flexed
# than 60 deg does not walk, so such a value is a typing error (e.g. a sitting angle), not a calibration.
MIN_STANDING_KNEE_DEG = -20.0
MAX_STANDING_KNEE_DEG = 60.0
# A calibration cannot be measured in the future; this much tolerates the clock of the recording device.
MAX_FUTURE_SKEW = timedelta(minutes=10)
MAX_NOTE_CHARS = 2000
MAX_AFFECTED_IDS = 100


class CalibrationIn(StrictIn):
    """A measured standing knee flexion of one leg."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"leg": "left", "standing_knee_deg": 7.5, "measured_at": "2026-11-20T10:15:00+01:00", "method": "goniometer",
         "note": "after physiotherapy"}]})

    leg: Leg
    standing_knee_deg: Annotated[FiniteFloat, Field(ge=MIN_STANDING_KNEE_DEG, le=MAX_STANDING_KNEE_DEG,
                                                    description="Knee flexion in quiet upright standing, degrees "
                                                                "(positive = flexion, negative = hyperextension)")]
    measured_at: PlausibleInstant = Field(description="When it was measured (ISO 8601 with offset, from 2000 on); "
                                                      "it applies to sessions that start at or after this instant")
    method: CalibrationMethod
    note: Annotated[str, Field(max_length=MAX_NOTE_CHARS)] | None = None

    @field_validator("measured_at")
    @classmethod
    def _not_in_future(cls, value: AwareDatetime) -> AwareDatetime:
        if value > utcnow() + MAX_FUTURE_SKEW:
            raise ValueError("a calibration cannot be measured in the future")
        return value


class CalibrationOut(OrmOut):
    """A recorded knee calibration."""

    id: str
    patient_id: str
    leg: Leg
    standing_knee_deg: float
    measured_at: UtcDatetime
    method: CalibrationMethod
    note: str | None
    created_at: UtcDatetime


class CalibrationCreated(CalibrationOut):
    """A new calibration and the processed sessions whose results it would change (not reprocessed)."""

    affected_sessions: int = Field(description="Processed sessions of this leg that a reprocess would now give "
                                               "this calibration (their stored results keep the old level until "
                                               "a clinician reprocesses them)")
    affected_session_ids: list[str] = Field(description=f"Those sessions' ids, newest first (at most "
                                                        f"{MAX_AFFECTED_IDS} listed)")


class CalibrationPage(BaseModel):
    """One page of calibrations, newest measurement first, and the cursor of the next."""

    items: list[CalibrationOut]
    next_cursor: str | None


class CalibrationUsed(BaseModel):
    """The calibration one leg of a session was processed with (a copy: it outlives a deleted calibration)."""

    id: str
    standing_knee_deg: float
    method: CalibrationMethod
    measured_at: UtcDatetime
