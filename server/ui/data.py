"""What the clinician pages need adapted from the services the API uses: the API's access rules and views with
the pages' arguments bound, the trend answers kept in memory, the knee-angle windows of every leg, the estimator
comparison in its short read. The views call the services (patients, trends, results) directly where a service
call is all they need. One query is still written here: the patient's calibrations, newest first (the
calibrations service has no list query; the API's list route writes its own).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from datetime import UTC, date, datetime
from typing import Any

from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.auth import service as auth_service
from server.auth.service import Principal, get_patient_for, get_session_for
from server.calibrations import service as calibration_service
from server.calibrations.models import KneeCalibration as KneeCalibrationRow
from server.calibrations.schemas import CalibrationIn
from server.patients.models import Patient
from server.results import compare as compare_service
from server.results import service as results_service
from server.results.models import KneeAngleTrace
from server.results.schemas import CompareOut
from server.results.service import TraceWindow
from server.sessions.models import Session
from server.trends import exports, service
from server.trends.attention import AttentionParams, attention_list
from server.trends.timeutil import Bucket, zone


def principal_for_token(db: DbSession, token: str) -> Principal | None:
    """The principal of a bearer token exactly as the API resolves it (hash lookup, revocation), or None."""
    return auth_service.principal_for_token(db, token)


def patient_for(db: DbSession, principal: Principal, patient_id: str) -> Patient:
    """The API's access rule: 404 (ProblemError) when the patient does not exist or is someone else's."""
    return get_patient_for(db, principal, patient_id)


def session_for(db: DbSession, principal: Principal, session_id: str) -> Session:
    """The API's access rule for sessions: 404 (ProblemError) unless the caller may see its patient."""
    return get_session_for(db, principal, session_id)


def completeness(db: DbSession, patient: Patient, days: int = 30) -> dict[str, Any]:
    """Days with data, last session and per-day strides (the API's completeness view)."""
    return service.patient_completeness(db, patient, days=days)


def attention(db: DbSession, principal: Principal, limit: int = 200) -> dict[str, Any]:
    """The API's attention list for this principal (admin: every patient)."""
    return attention_list(db, clinician_id=None if principal.is_admin else principal.clinician_id,
                          params=AttentionParams(), limit=limit)


_cache: OrderedDict[tuple, dict[str, Any]] = OrderedDict()
_cache_lock = threading.Lock()
CACHE_SIZE = 128  # trend/symmetry answers (~0.1-0.3 MB each for a year of daily buckets)


def _version(db: DbSession, patient: Patient) -> tuple:
    """What a patient's trend answers depend on: the patient's summaries, time zone and affected leg."""
    return patient.id, patient.timezone, patient.affected_leg, *service.summaries_version(db, patient.id)


def _cached(key: tuple, compute: Any) -> dict[str, Any]:
    with _cache_lock:
        if key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
    value = compute()
    with _cache_lock:
        _cache[key] = value
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return value


def clear_cache() -> None:
    """Forget every cached trend answer (tests, and when summaries change wholesale)."""
    with _cache_lock:
        _cache.clear()


def trends(db: DbSession, patient: Patient, metric: str, leg: str, bucket: Bucket) -> dict[str, Any]:
    """One metric of one leg over the patient's whole history (the API's trends view), kept in memory until the
    patient's trend summaries change (a processed, reprocessed or deleted session)."""
    key = ("trends", *_version(db, patient), metric, leg, bucket)
    return _cached(key, lambda: service.patient_trends(db, patient, metric_name=metric, leg=leg, bucket=bucket,
                                                       start=None, end=None))


def symmetry(db: DbSession, patient: Patient, metric: str, bucket: Bucket) -> dict[str, Any]:
    """Affected against other leg per bucket (the API's symmetry view), cached like :func:`trends`."""
    key = ("symmetry", *_version(db, patient), metric, bucket)
    return _cached(key, lambda: service.patient_symmetry(db, patient, metric_name=metric, bucket=bucket,
                                                         start=None, end=None))


def knee_angle(stored: dict[str, KneeAngleTrace], *, start_s: float | None = None, end_s: float | None = None,
               max_points: int = 1600) -> list[TraceWindow]:
    """The continuous knee angle of each leg of a session's stored traces (:func:`server.results.service.traces`)
    in [start_s, end_s], min/max down-sampled as the API does."""
    out = []
    for _, row in sorted(stored.items()):
        if row.n:
            out.append(results_service.trace_window(row, start_s=start_s, end_s=end_s, max_points=max_points))
    return out


def compare(factory: sessionmaker[DbSession], principal: Principal, session: Session) -> CompareOut:
    """Every estimator on this session through the API's compare service: the raw data are read in a short
    transaction of their own, the pipeline runs without a database session, answers are cached in memory."""
    names = compare_service.requested_estimators(None)
    inp = compare_service.load_input(factory, principal, session.id, names)
    try:
        return compare_service.run_compare(inp)
    except LookupError:  # evicted from the cache between the two calls: read the data after all
        return compare_service.run_compare(
            compare_service.load_input(factory, principal, session.id, names, with_streams=True))


def strides_csv(db: DbSession, patient: Patient) -> Any:
    """The API's CSV export of every stride, as an iterator of text chunks."""
    return exports.strides_csv(db, patient, None, None)


def fhir_bundle(db: DbSession, patient: Patient, identifier_system: str) -> dict[str, Any]:
    """The API's FHIR R4 Bundle of daily Observations."""
    return exports.fhir_bundle(db, patient, None, None, identifier_system=identifier_system)


def local_today(patient: Patient) -> date:
    """Today in the patient's time zone."""
    return datetime.now(UTC).astimezone(zone(patient.timezone)).date()


def calibrations(db: DbSession, patient: Patient) -> list[KneeCalibrationRow]:
    """The patient's knee calibrations, newest measurement first."""
    return list(db.scalars(calibration_service.calibrations_of(patient.id)))


def record_calibration(db: DbSession, principal: Principal, patient: Patient, body: CalibrationIn) -> int:
    """Record a calibration exactly as the API does; returns how many processed sessions a reprocess would change."""
    _, affected = calibration_service.record(db, patient.id, body, principal.token_id)
    db.commit()
    return len(affected)
