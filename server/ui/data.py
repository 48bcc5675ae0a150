"""Everything the clinician pages read, through the service layer the API uses (one import point for the pages).

Functions that only wrap a service are thin on purpose. Strides, knee-angle windows and gait cycles come from
:mod:`server.results.service`, which the API's result routes use too. The few queries still written here (marked
"query lives here": the latest per-leg values, per-session peaks and the first processed session) have no API
route yet. Patient and session lists are the patients service's queries, in numbered pages.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from datetime import UTC, date, datetime
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.auth import service as auth_service
from server.auth.service import Principal, get_patient_for, get_session_for
from server.calibrations import service as calibration_service
from server.calibrations.models import KneeCalibration as KneeCalibrationRow
from server.calibrations.schemas import CalibrationIn
from server.patients import service as patient_service
from server.patients.models import Patient
from server.results import compare as compare_service
from server.results import service as results_service
from server.results.schemas import CompareOut
from server.results.service import Cycle, TraceWindow
from server.sessions.models import Session
from server.trends import exports, service
from server.trends.attention import AttentionParams, attention_list
from server.trends.metrics import METRICS, MIN_QUALITY
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.timeutil import Bucket, zone
from server.utc import as_utc

# The metrics of the patient page, in the order a physiotherapist reads them.
TREND_METRICS = ("peak_swing_flexion_deg", "rom_deg", "min_flexion_deg", "strides_per_day")
OVERVIEW_METRICS = ("peak_swing_flexion_deg", "rom_deg")


def principal_for_token(db: DbSession, token: str) -> Principal | None:
    """The principal of a bearer token exactly as the API resolves it (hash lookup, revocation), or None."""
    return auth_service.principal_for_token(db, token)


def patient_for(db: DbSession, principal: Principal, patient_id: str) -> Patient:
    """The API's access rule: 404 (ProblemError) when the patient does not exist or is someone else's."""
    return get_patient_for(db, principal, patient_id)


def session_for(db: DbSession, principal: Principal, session_id: str) -> Session:
    """The API's access rule for sessions: 404 (ProblemError) unless the caller may see its patient."""
    return get_session_for(db, principal, session_id)


@dataclass(frozen=True)
class PatientPage:
    """One page of the patient list with the total count."""

    items: list[Patient]
    total: int
    offset: int
    limit: int


def list_patients(db: DbSession, principal: Principal, *, search: str = "", offset: int = 0,
                  limit: int = 25) -> PatientPage:
    """The principal's patients (admin: all), oldest first, optionally those whose external id contains
    ``search`` (the API's list query, :func:`server.patients.service.patients_of`, in numbered pages)."""
    stmt = patient_service.patients_of(principal, search)
    rows = db.scalars(stmt.order_by(Patient.created_at, Patient.id).offset(offset).limit(limit)).all()
    return PatientPage(list(rows), patient_service.count(db, stmt), offset, limit)


def latest_values(db: DbSession, patient_ids: list[str]) -> dict[str, dict[str, dict[str, dict[str, Any]]]]:
    """{patient: {leg: {metric: {mean, at}}}}: the mean of the most recent session with included strides, per
    patient, leg and metric, in one query for a page of patients. Query lives here (no service has "latest value"
    yet); it reads the trend summaries along their (patient, metric, leg, time) index."""
    if not patient_ids:
        return {}
    m = TrendMetricValues
    last = (select(m.patient_id, m.metric, m.leg, func.max(m.started_at).label("t"))
            .where(m.patient_id.in_(patient_ids), m.metric.in_(OVERVIEW_METRICS), m.n_included > 0)
            .group_by(m.patient_id, m.metric, m.leg).subquery())
    rows = db.execute(select(m.patient_id, m.leg, m.metric, m.mean, m.started_at).join(
        last, (last.c.patient_id == m.patient_id) & (last.c.metric == m.metric) & (last.c.leg == m.leg)
        & (last.c.t == m.started_at)).where(m.n_included > 0)).all()
    out: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for pid, leg, metric, mean, at in rows:
        if mean is not None:
            out.setdefault(pid, {}).setdefault(leg, {})[metric] = {"mean": float(mean), "at": as_utc(at)}
    return out


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


def _summaries_version(db: DbSession, patient: Patient) -> tuple:
    """What the trend answers of a patient depend on: the summary rows (every processing run rewrites its legs
    with a new ``refreshed_at``; a deleted session removes them), the time zone and the affected leg."""
    n, last = db.execute(select(func.count(), func.max(TrendSessionLeg.refreshed_at))
                         .where(TrendSessionLeg.patient_id == patient.id)).one()
    return patient.id, patient.timezone, patient.affected_leg, n, str(last)


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
    key = ("trends", *_summaries_version(db, patient), metric, leg, bucket)
    return _cached(key, lambda: service.patient_trends(db, patient, metric_name=metric, leg=leg, bucket=bucket,
                                                       start=None, end=None))


def symmetry(db: DbSession, patient: Patient, metric: str, bucket: Bucket) -> dict[str, Any]:
    """Affected against other leg per bucket (the API's symmetry view), cached like :func:`trends`."""
    key = ("symmetry", *_summaries_version(db, patient), metric, bucket)
    return _cached(key, lambda: service.patient_symmetry(db, patient, metric_name=metric, bucket=bucket,
                                                         start=None, end=None))


def legs_with_data(db: DbSession, patient: Patient) -> list[str]:
    """Legs of the patient that have trend summaries."""
    return service.legs_with_data(db, patient.id)


def list_sessions(db: DbSession, patient: Patient, *, offset: int = 0, limit: int = 20) -> tuple[list[Session], int]:
    """The patient's sessions, newest first, and their total (the API's list query in numbered pages)."""
    stmt = patient_service.sessions_of(patient.id)
    rows = db.scalars(stmt.order_by(Session.started_at.desc(), Session.id.desc()).offset(offset).limit(limit)).all()
    return list(rows), patient_service.count(db, stmt)


def session_peaks(db: DbSession, session_ids: list[str]) -> dict[str, dict[str, tuple[int, float | None]]]:
    """{session: {leg: (trustworthy strides, median peak swing flexion of them)}} from the trend summaries (so a
    stride that does not count in the trends does not count here either). Query lives here."""
    m = TrendMetricValues
    out: dict[str, dict[str, tuple[int, float | None]]] = {}
    if not session_ids:
        return out
    for sid, leg, n, median in db.execute(select(m.session_id, m.leg, m.n_included, m.median).where(
            m.session_id.in_(session_ids), m.metric == "peak_swing_flexion_deg")):
        out.setdefault(sid, {})[leg] = (int(n), None if median is None else float(median))
    return out


def first_done_session(db: DbSession, patient: Patient) -> Session | None:
    """The patient's earliest processed session (the reference of the gait-cycle plot). Query lives here."""
    return db.scalar(select(Session).where(Session.patient_id == patient.id, Session.status == "done")
                     .order_by(Session.started_at, Session.id).limit(1))


def strides(db: DbSession, session: Session) -> list[Any]:
    """Every stored stride of the session by leg and index (the results service's core rows)."""
    return results_service.strides(db, session.id)


def exclusions(rows: list[Any]) -> list[list[str]]:
    """Per stride, why it does not count in the trends (empty: it counts), in the codes of
    :func:`server.trends.exports._exclusions` (``quality<0.5``, ``implausible:<metric>``).

    The same rule as that function and as :func:`server.trends.summaries.summarise_leg`, evaluated on whole
    columns with the same :class:`Metric` methods (per-stride calls cost ~60 us each, too slow for a long session);
    tests/ui/test_data.py checks it against ``exports._exclusions`` stride by stride."""
    if not rows:
        return []
    quality = np.array([np.nan if r.quality is None else r.quality for r in rows], dtype=np.float64)
    out: list[list[str]] = [[] for _ in rows]
    low = ~(quality >= MIN_QUALITY)
    for i in np.flatnonzero(low):
        out[i].append(f"quality<{MIN_QUALITY:g}")
    for name, metric in METRICS.items():
        if metric.column is None:
            continue
        raw = np.array([np.nan if getattr(r, metric.column) is None else getattr(r, metric.column) for r in rows],
                       dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            bad = ~metric.plausible(metric.values(raw)) & ~low
        for i in np.flatnonzero(bad):
            out[i].append(f"implausible:{name}")
    return out


def knee_angle(db: DbSession, session: Session, *, start_s: float | None = None, end_s: float | None = None,
               max_points: int = 1600) -> list[TraceWindow]:
    """The continuous knee angle of each leg in [start_s, end_s], min/max down-sampled as the API does."""
    out = []
    for _, row in sorted(results_service.traces(db, session.id).items()):
        if row.n:
            out.append(results_service.trace_window(row, start_s=start_s, end_s=end_s, max_points=max_points))
    return out


def gait_cycles(db: DbSession, session: Session, rows: list[Any] | None = None,
                excluded: list[list[str]] | None = None) -> dict[str, Cycle]:
    """Per leg, the knee angle over the gait cycle of the strides that count in the trends (the results
    service's computation). ``rows``/``excluded``: the session's :func:`strides` and :func:`exclusions` when the
    caller has them."""
    if rows is None:
        rows = strides(db, session)
    if excluded is None:
        excluded = exclusions(rows)
    return results_service.gait_cycles(db, session.id, rows, excluded)


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
    return list(db.scalars(select(KneeCalibrationRow).where(KneeCalibrationRow.patient_id == patient.id)
                           .order_by(KneeCalibrationRow.measured_at.desc(), KneeCalibrationRow.id.desc())))


def record_calibration(db: DbSession, principal: Principal, patient: Patient, body: CalibrationIn) -> int:
    """Record a calibration exactly as the API does; returns how many processed sessions a reprocess would change."""
    _, affected = calibration_service.record(db, patient.id, body, principal.token_id)
    db.commit()
    return len(affected)
