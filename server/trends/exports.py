"""Exports: every stride as CSV (for spreadsheets) and daily summaries as a FHIR R4 Bundle of Observations.

FHIR coding choices (verified, not guessed):
- bodySite: SNOMED CT 82169009 "Structure of left knee region" and 6757004 "Structure of right knee region"
  (system http://snomed.info/sct).
- valueQuantity in UCUM (http://unitsofmeasure.org): ``deg``, ``s``, ``%``, ``/min``.
- category: ``activity`` of http://terminology.hl7.org/CodeSystem/observation-category.
- code: the metrics keep the service's own CodeSystem ``LOCAL_CODE_SYSTEM``. We found no LOINC code we could verify
  for knee flexion angles, knee range of motion during gait, stride time or cadence measured by wearables; the
  activity codes LOINC has (e.g. 41950-7 "Number of steps in 24 hour, Measured") describe whole-day step counts,
  which gaitmon does not measure (it sees recorded sessions only), so using them would misstate the observation.
- Patient: the clinic's ``external_id`` (its MRN) as ``identifier`` with type ``MR`` of HL7 v2 table 0203
  (http://terminology.hl7.org/CodeSystem/v2-0203) and the configured system (``GAITMON_FHIR_IDENTIFIER_SYSTEM``);
  gaitmon's own id as a secondary identifier. Observations name the patient by that identifier and by reference to
  the Patient entry of the Bundle, so a receiving system can file them without knowing gaitmon's ids.
- device: one Device entry (the thigh and shank IMUs with gaitmon's stride analysis, algorithm versions listed).
- effectivePeriod: the patient's local day the daily summary covers (start inclusive, end exclusive).
"""

from __future__ import annotations

import csv
import io
import uuid
from collections import defaultdict
from collections.abc import Iterator
from datetime import date, datetime, timedelta
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

from server.codec import decode_values
from server.enums import StrideActivity
from server.numbers import finite_round
from server.patients.models import Patient
from server.results.models import Stride
from server.results.stride_record import STRIDE_UNITS, STRIDE_VALUE_FIELDS
from server.sessions.models import Session
from server.trends import stats
from server.trends.metrics import METRICS, Metric, stride_exclusions
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.timeutil import local_date, local_midnight, zone
from server.utc import as_utc, utcnow

LOCAL_CODE_SYSTEM = "urn:gaitmon:codesystem:gait-metric"
PATIENT_ID_SYSTEM = "urn:gaitmon:patient-id"  # gaitmon's own patient ids (a secondary identifier)
IDENTIFIER_TYPE = "http://terminology.hl7.org/CodeSystem/v2-0203"
SNOMED = "http://snomed.info/sct"
UCUM = "http://unitsofmeasure.org"
KNEE_SITE = {
    "left": ("82169009", "Structure of left knee region"),
    "right": ("6757004", "Structure of right knee region"),
}
FHIR_METRICS = ("peak_swing_flexion_deg", "rom_deg", "min_flexion_deg", "stance_flexion_deg", "stride_time_s",
                "cadence_steps_per_min")
_NS = uuid.UUID("1b7d7c3e-3f0e-4b8e-9d0a-6a1f3c2b9e55")  # namespace of the stable Observation ids

# The stride's value fields as the pipeline declares them, with the derived cadence next to the stance share.
_CADENCE_AFTER = "stance_pct"
VALUE_COLUMNS: tuple[str, ...] = tuple(c for name in STRIDE_VALUE_FIELDS for c in (
    (name, "cadence_steps_per_min") if name == _CADENCE_AFTER else (name,)))
_DECIMALS = {"s": 4, "%": 2, "deg": 2, "steps/min": 2}
_UNITS = {**STRIDE_UNITS, "cadence_steps_per_min": METRICS["cadence_steps_per_min"].unit}
CSV_COLUMNS = [
    "session_id", "client_session_id", "leg", "index", "started_at", "local_date", *VALUE_COLUMNS, "estimator",
    "quality", "quality_reasons", "included", "excluded_because", "activity", "fallback",
]


def _num(x: float | None, nd: int = 4) -> str:
    v = finite_round(x, nd)
    return "" if v is None else f"{v:.{nd}f}".rstrip("0").rstrip(".")


def _text_cell(value: str | None) -> str:
    """A client-chosen text for a CSV cell: one starting with ``= + - @``, a tab or a carriage return is prefixed
    with ``'`` so that a spreadsheet shows it instead of running it as a formula (OWASP "CSV injection")."""
    text = value or ""
    return "'" + text if text[:1] in ("=", "+", "-", "@", "\t", "\r") else text


def strides_csv(db: DbSession, patient: Patient, start: datetime | None, end: datetime | None,
                chunk: int = 2000, *, activity: str = StrideActivity.walking) -> Iterator[str]:
    """Stream the patient's strides of one activity as RFC 4180 CSV (header first; times ISO 8601 in the
    patient's zone)."""
    tz = zone(patient.timezone)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(CSV_COLUMNS)
    yield buf.getvalue()
    # Core rows, not ORM objects: a year of strides is ~10^5-10^6 rows.
    q = (select(*Stride.__table__.c, Session.client_session_id).join(Session, Session.id == Stride.session_id)
         .where(Stride.patient_id == patient.id, Stride.activity == activity))
    if start is not None:
        q = q.where(Stride.started_at >= as_utc(start))
    if end is not None:
        q = q.where(Stride.started_at < as_utc(end))
    q = q.order_by(Stride.started_at, Stride.leg, Stride.index).execution_options(yield_per=chunk)
    buf = io.StringIO()
    w = csv.writer(buf)
    for rows in db.execute(q).partitions():
        for row, excl in zip(rows, stride_exclusions(rows), strict=True):
            s = row._mapping
            local = as_utc(s["started_at"]).astimezone(tz)
            cadence = 120.0 / s["duration_s"] if s["duration_s"] else None
            values = {**s, "cadence_steps_per_min": cadence}
            w.writerow([
                s["session_id"], _text_cell(s["client_session_id"]), s["leg"], s["index"], local.isoformat(),
                local.date().isoformat(), *(_num(values[c], _DECIMALS[_UNITS[c]]) for c in VALUE_COLUMNS),
                s["estimator"], _num(s["quality"], 3),
                ";".join(s["quality_reasons"] or []), "0" if excl else "1", ";".join(excl), s["activity"],
                "1" if s["fallback"] else "0",
            ])
        yield buf.getvalue()
        buf.seek(0)
        buf.truncate()


def _quantity(metric: Metric, value: float) -> dict[str, Any]:
    return {"value": round(float(value), 3), "unit": metric.unit, "system": UCUM, "code": metric.ucum}


def _component(code: str, display: str, value: dict[str, Any] | int) -> dict[str, Any]:
    out: dict[str, Any] = {"code": {"coding": [{"system": LOCAL_CODE_SYSTEM, "code": code, "display": display}]}}
    if isinstance(value, int):
        out["valueInteger"] = value
    else:
        out["valueQuantity"] = value
    return out


def _entry_uuid(key: str) -> str:
    try:
        return str(uuid.UUID(hex=key))
    except ValueError:
        return str(uuid.uuid5(_NS, key))


def patient_entry(patient: Patient, identifier_system: str) -> dict[str, Any]:
    """The Bundle's Patient: the clinic's identifier (MRN) when known, gaitmon's id as a secondary one."""
    identifiers: list[dict[str, Any]] = []
    if patient.external_id:
        identifiers.append({"use": "usual", "type": {"coding": [{"system": IDENTIFIER_TYPE, "code": "MR",
                                                                 "display": "Medical record number"}]},
                            "system": identifier_system, "value": patient.external_id})
    identifiers.append({"use": "secondary", "system": PATIENT_ID_SYSTEM, "value": patient.id})
    resource: dict[str, Any] = {"resourceType": "Patient", "id": patient.id, "identifier": identifiers}
    if patient.display_name:
        resource["name"] = [{"text": patient.display_name}]
    return {"fullUrl": f"urn:uuid:{_entry_uuid(patient.id)}", "resource": resource}


def subject_reference(patient: Patient, patient_full_url: str, identifier_system: str) -> dict[str, Any]:
    """Observation.subject: the Bundle's Patient entry, and the business identifier a receiver files by."""
    ref: dict[str, Any] = {"reference": patient_full_url}
    if patient.external_id:
        ref["identifier"] = {"system": identifier_system, "value": patient.external_id}
    if patient.display_name:
        ref["display"] = patient.display_name
    return ref


def device_entry(patient: Patient, patient_full_url: str, versions: list[str]) -> dict[str, Any]:
    """The measuring device: per leg a thigh and a shank IMU, with gaitmon's stride analysis (its versions)."""
    did = str(uuid.uuid5(_NS, f"{patient.id}/device"))
    resource: dict[str, Any] = {
        "resourceType": "Device", "id": did,
        "deviceName": [{"name": "gaitmon wearable gait analysis", "type": "user-friendly-name"}],
        "type": {"text": "Thigh and shank inertial measurement units with gaitmon stride analysis software"},
        "patient": {"reference": patient_full_url},
    }
    if versions:
        resource["version"] = [{"type": {"text": "algorithm"}, "value": v} for v in versions]
    return {"fullUrl": f"urn:uuid:{did}", "resource": resource}


def daily_observations(db: DbSession, patient: Patient, start: datetime | None, end: datetime | None,
                       metrics: tuple[str, ...] = FHIR_METRICS, *, activity: str = StrideActivity.walking,
                       subject: dict[str, Any] | None = None,
                       device: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """One Observation per local day, leg and metric: the day's mean as value, median/sd/p10/p90/count as
    components. Only included (quality-passing, plausible) strides count. ``subject`` and ``device`` are the
    references to put in each (default: ``Patient/<gaitmon id>``, no device)."""
    tz = zone(patient.timezone)
    m, s = TrendMetricValues, TrendSessionLeg
    q = (select(m.metric, m.leg, m.started_at, m.session_id, m.n_included, m.n_implausible, m.values,
                s.n_low_quality, s.algorithm_version)
         .join(s, (s.session_id == m.session_id) & (s.leg == m.leg) & (s.activity == m.activity))
         .where(m.patient_id == patient.id, m.metric.in_(metrics), m.activity == activity))
    if start is not None:
        q = q.where(m.started_at >= as_utc(start))
    if end is not None:
        q = q.where(m.started_at < as_utc(end))
    groups: dict[tuple[str, str, date], list[Any]] = defaultdict(list)
    for r in db.execute(q.order_by(m.started_at)):
        groups[(r.metric, r.leg, local_date(r.started_at, tz))].append(r)
    issued = utcnow().replace(microsecond=0).isoformat()
    out = []
    for (name, leg, day), rows in sorted(groups.items(), key=lambda kv: (kv[0][2], kv[0][1], kv[0][0])):
        metric = METRICS[name]
        values = np.concatenate([decode_values(r.values) for r in rows]).astype(np.float64)
        d = stats.describe(values)
        if d.n == 0 or leg not in KNEE_SITE:
            continue
        # Walking keeps the id it always had; other activities get ids of their own.
        suffix = "" if activity == StrideActivity.walking else f"/{activity}"
        oid = str(uuid.uuid5(_NS, f"{patient.id}/{leg}/{name}/{day.isoformat()}{suffix}"))
        code, site = KNEE_SITE[leg]
        versions = sorted({r.algorithm_version for r in rows if r.algorithm_version})
        n_excluded = sum(r.n_implausible + (r.n_low_quality or 0) for r in rows)
        components = [_component("n-strides", "Included strides", int(d.n)),
                      _component("n-excluded", "Excluded strides", int(n_excluded)),
                      _component("n-sessions", "Sessions", len({r.session_id for r in rows})),
                      _component("median", "Median", _quantity(metric, d.median))]
        for key, label, val in (("sd", "Standard deviation", d.sd), ("p10", "10th percentile", d.p10),
                                ("p90", "90th percentile", d.p90)):
            if val is not None:
                components.append(_component(key, label, _quantity(metric, val)))
        out.append({
            "fullUrl": f"urn:uuid:{oid}",
            "resource": {
                "resourceType": "Observation", "id": oid, "status": "final",
                "category": [{"coding": [{
                    "system": "http://terminology.hl7.org/CodeSystem/observation-category", "code": "activity",
                    "display": "Activity"}]}],
                "code": {"coding": [{"system": LOCAL_CODE_SYSTEM, "code": name, "display": metric.title}],
                         "text": f"{metric.title}, daily mean ({leg} leg{'' if not suffix else ', ' + activity})"},
                "subject": subject or {"reference": f"Patient/{patient.id}"},
                **({"device": device} if device else {}),
                "effectivePeriod": {"start": local_midnight(day, tz).isoformat(),
                                    "end": local_midnight(day + timedelta(days=1), tz).isoformat()},
                "issued": issued,
                "valueQuantity": _quantity(metric, d.mean),
                "bodySite": {"coding": [{"system": SNOMED, "code": code, "display": site}],
                             "text": f"{leg.capitalize()} knee"},
                "method": {"text": "Thigh and shank IMUs; gaitmon stride analysis"
                                   + (f" (algorithm {', '.join(versions)})" if versions else "")},
                "component": components,
            },
        })
    return out


def _algorithm_versions(db: DbSession, patient: Patient, start: datetime | None, end: datetime | None) -> list[str]:
    s = TrendSessionLeg
    q = select(s.algorithm_version).where(s.patient_id == patient.id, s.algorithm_version.is_not(None)).distinct()
    if start is not None:
        q = q.where(s.started_at >= as_utc(start))
    if end is not None:
        q = q.where(s.started_at < as_utc(end))
    return sorted(db.scalars(q).all())


def fhir_bundle(db: DbSession, patient: Patient, start: datetime | None, end: datetime | None,
                metrics: tuple[str, ...] = FHIR_METRICS, *, identifier_system: str,
                activity: str = StrideActivity.walking) -> dict[str, Any]:
    """A FHIR R4 collection Bundle of one activity: the Patient, the Device, and the daily Observations referring
    to both."""
    pat = patient_entry(patient, identifier_system)
    dev = device_entry(patient, pat["fullUrl"], _algorithm_versions(db, patient, start, end))
    observations = daily_observations(
        db, patient, start, end, metrics, activity=activity,
        subject=subject_reference(patient, pat["fullUrl"], identifier_system),
        device={"reference": dev["fullUrl"], "display": "gaitmon wearable gait analysis"})
    return {"resourceType": "Bundle", "id": str(uuid.uuid4()), "type": "collection",
            "timestamp": utcnow().replace(microsecond=0).isoformat(),
            "entry": [pat, dev, *observations]}

