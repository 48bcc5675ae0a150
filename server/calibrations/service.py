"""Which calibration applies to a session, its form for the pipeline, and which processed sessions a change affects.

The rule: a leg of a session is processed with that leg's latest calibration measured at or before the session
started (``measured_at <= started_at``; ties: the one recorded last). A calibration measured after a session does
not rewrite the past: without an older one the session keeps the assumed standing flexion. Creating or deleting
a calibration never reprocesses anything by itself; it reports the processed sessions whose calibration would
differ on a reprocess, and the clinician reprocesses those (``POST /v1/sessions/{id}/reprocess``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import Select, select
from sqlalchemy.orm import Session as DbSession

from pipeline.types import KneeCalibration as PipelineCalibration
from server.calibrations.models import KneeCalibration
from server.calibrations.schemas import CalibrationIn, CalibrationUsed
from server.enums import Leg, SessionStatus
from server.sessions.models import Session
from server.utc import as_utc

# The key of the processing summary that records, per leg, the calibration a session was processed with.
SUMMARY_KEY = "calibration"


# The order calibrations are listed in, by the API and the pages: newest measurement first (keyset: id breaks ties).
LIST_ORDER = (KneeCalibration.measured_at.desc(), KneeCalibration.id.desc())


def calibrations_of(patient_id: str, leg: Leg | None = None) -> Select[tuple[KneeCalibration]]:
    """The patient's calibrations (optionally of one leg), in :data:`LIST_ORDER`."""
    stmt = select(KneeCalibration).where(KneeCalibration.patient_id == patient_id)
    if leg is not None:
        stmt = stmt.where(KneeCalibration.leg == leg)
    return stmt.order_by(*LIST_ORDER)


def _newest_first(rows: Iterable[KneeCalibration]) -> list[KneeCalibration]:
    return sorted(rows, key=lambda c: (as_utc(c.measured_at), as_utc(c.created_at), c.id), reverse=True)


def valid_at(calibrations: Iterable[KneeCalibration], started_at: datetime) -> KneeCalibration | None:
    """Of one leg's calibrations, the one valid for a session that started at ``started_at`` (or None)."""
    start = as_utc(started_at)
    return next((c for c in _newest_first(calibrations) if as_utc(c.measured_at) <= start), None)


def applicable(db: DbSession, patient_id: str, started_at: datetime) -> dict[str, KneeCalibration]:
    """Per leg, the calibration valid for a session of the patient that started at ``started_at``."""
    start = as_utc(started_at)
    out: dict[str, KneeCalibration] = {}
    for leg in Leg:
        row = db.scalar(select(KneeCalibration)
                        .where(KneeCalibration.patient_id == patient_id, KneeCalibration.leg == leg,
                               KneeCalibration.measured_at <= start)
                        .order_by(KneeCalibration.measured_at.desc(), KneeCalibration.created_at.desc(),
                                  KneeCalibration.id.desc())
                        .limit(1))
        if row is not None:
            out[str(leg)] = row
    return out


def for_pipeline(calibrations: Mapping[str, KneeCalibration]) -> dict[str, PipelineCalibration]:
    """The calibrations in the pipeline's form (its diagnostics echo the id)."""
    return {leg: PipelineCalibration(standing_knee_deg=float(c.standing_knee_deg), method=c.method,
                                     calibration_id=c.id)
            for leg, c in calibrations.items()}


def used_block(calibrations: Mapping[str, KneeCalibration], legs: Iterable[str]) -> dict[str, Any]:
    """The summary's record of the calibration each leg was processed with (None: the level was assumed)."""
    return {leg: (CalibrationUsed.model_validate(calibrations[leg], from_attributes=True).model_dump(mode="json")
                  if leg in calibrations else None)
            for leg in sorted(set(legs))}


def _used_id(summary: Mapping[str, Any] | None, leg: str) -> str | None:
    block = ((summary or {}).get(SUMMARY_KEY) or {}).get(leg)
    return block.get("id") if isinstance(block, dict) else None


def affected_sessions(db: DbSession, patient_id: str, leg: str, since: datetime) -> list[str]:
    """Processed sessions of the patient, newest first, whose ``leg`` was processed with another calibration than
    the one valid for it now. Only sessions that started at or after ``since`` (the measurement of the calibration
    created or deleted) can be affected."""
    calibrations = db.scalars(select(KneeCalibration).where(KneeCalibration.patient_id == patient_id,
                                                            KneeCalibration.leg == leg)).all()
    rows = db.execute(select(Session.id, Session.started_at, Session.summary)
                      .where(Session.patient_id == patient_id, Session.status == SessionStatus.done,
                             Session.started_at >= as_utc(since))
                      .order_by(Session.started_at.desc(), Session.id.desc())).all()
    out = []
    for sid, started_at, summary in rows:
        if leg not in ((summary or {}).get("legs") or {}):
            continue  # that leg has no results in this session
        now = valid_at(calibrations, started_at)
        if (now.id if now is not None else None) != _used_id(summary, leg):
            out.append(sid)
    return out


def record(db: DbSession, patient_id: str, body: CalibrationIn, token_id: str) -> tuple[KneeCalibration, list[str]]:
    """Store a calibration (measured_at in UTC: SQLite drops the offset of an aware datetime instead of converting
    it) and list the processed sessions of that leg a reprocess would change. Flushes; the caller commits."""
    cal = KneeCalibration(patient_id=patient_id, leg=body.leg, standing_knee_deg=body.standing_knee_deg,
                          measured_at=body.measured_at.astimezone(UTC), method=body.method, note=body.note,
                          recorded_by_token_id=token_id)
    db.add(cal)
    db.flush()
    return cal, affected_sessions(db, patient_id, body.leg, cal.measured_at)
