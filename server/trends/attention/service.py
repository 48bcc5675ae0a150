"""The attention list: which patients need the clinician, with the reason and the numbers behind each flag.

Three lean reads of the precomputed per session-leg summaries (session means of one metric, sensor evidence of the
sensor window, failed runs) plus the last session per patient; the flags are pure functions
(:mod:`server.trends.attention.rules`), so the cost grows with patients and sessions in the windows, never with
strides.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import replace
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session as DbSession

from server.enums import SessionStatus
from server.patients.models import Patient
from server.sessions.models import Session
from server.trends import stats
from server.trends.attention import rules
from server.trends.attention.params import PRESETS, SESSION_SD_PRIOR, AttentionParams
from server.trends.metrics import METRICS, MIN_STRIDES_PER_SESSION, Metric
from server.trends.models import AttentionEvidence, TrendMetricValues, TrendSessionLeg
from server.utc import as_utc, utcnow

_Raw = tuple[float, int, float, float | None]  # (t_days before now, n, mean, sd) of one session


def _points(db: DbSession, owned: list[Any], metrics: list[str], activity: str,
            since: datetime, now: datetime) -> dict[str, dict[str, dict[str, list[_Raw]]]]:
    """Session means per patient, metric and leg since ``since``: {pid: {metric: {leg: [raw point]}}}."""
    m = TrendMetricValues
    q = (select(m.patient_id, m.metric, m.leg, m.started_at, m.n_included, m.mean, m.sd)
         .join(Patient, Patient.id == m.patient_id)
         .where(*owned, m.metric.in_(metrics), m.activity == activity, m.n_included >= MIN_STRIDES_PER_SESSION,
                m.started_at >= since, m.started_at <= now))
    out: dict[str, dict[str, dict[str, list[_Raw]]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for pid, metric, leg, t, n, mean, sd in db.execute(q):
        out[pid][metric][leg].append(((as_utc(t) - now).total_seconds() / 86400.0, n, mean, sd))
    return out


def _sensor_rows(db: DbSession, owned: list[Any], since: datetime) -> dict[str, list[rules.SessionLegEvidence]]:
    s = TrendSessionLeg
    q = (select(s.patient_id, s.started_at, s.leg, s.n_strides, s.n_expected, s.n_low_quality, s.n_fallback,
                s.n_implausible, s.n_gaps, s.walking_s, s.coverage)
         .join(Patient, Patient.id == s.patient_id).where(*owned, s.started_at >= since))
    out: dict[str, list[rules.SessionLegEvidence]] = defaultdict(list)
    for pid, t, leg, n, n_exp, low, fb, impl, gaps, walk, cov in db.execute(q):
        out[pid].append(rules.SessionLegEvidence(t, leg, n or 0, max(n_exp or 0, n or 0), low or 0, fb or 0,
                                                 impl or 0, gaps or 0, float(walk or 0.0), cov))
    return out


def _as_points(raw: list[tuple[float, int, float, float | None]], since_days: float) -> list[stats.Point]:
    return [stats.Point(t, n, mean, sd) for t, n, mean, sd in raw if t >= since_days]


def leg_flag(p: AttentionParams, metric: Metric, series: dict[str, dict[str, list[_Raw]]],
             leg: str) -> dict[str, Any] | None:
    """The trend flag of one leg (declining, else improving, else stalled), or None.
    ``series``: {metric: {leg: raw points}} of the metric and its level-free companion."""
    per_leg = series.get(metric.name, {})
    companion = rules.LEVEL_FREE_COMPANION.get(metric.name) if p.level_free_test else None
    trend = _as_points(per_leg.get(leg, []), -2.0 * p.window_days)
    other = series.get(companion, {}).get(leg, []) if companion else []
    tested = _as_points(other, -2.0 * p.window_days) if companion else None
    if tested is not None and len(tested) != len(trend):
        tested = None  # the companion must describe the same sessions
    plateau = _as_points(per_leg.get(leg, []), -7.0 * p.stalled_weeks)
    flag = (rules.change_flag("declining", p, metric, leg, trend, tested, companion)
            or rules.change_flag("improving", p, metric, leg, trend, tested, companion)
            or rules.stalled_flag(p, metric, leg, plateau,
                                  _as_points(other, -7.0 * p.stalled_weeks) if companion else None, companion))
    if flag:
        flag["severity"] = rules.SEVERITY[flag["kind"]]
    return flag


def assessed_legs(affected: str | None, legs_with_data: list[str]) -> list[str]:
    """The affected leg when it has data, otherwise every leg with data."""
    return [affected] if affected in legs_with_data else sorted(legs_with_data)


def _ranked(flags: list[dict[str, Any]]) -> list[dict[str, Any]]:
    for f in flags:
        f["severity"] = rules.SEVERITY[f["kind"]]
    flags.sort(key=lambda f: (-f["severity"], -(f.get("effect") or 0.0)))
    return flags


def patient_flags(p: AttentionParams, metric: Metric, now: datetime, series: dict[str, dict[str, list[_Raw]]],
                  affected: str | None, last: datetime | None, created: datetime, prescribed: float | None,
                  sensor_rows: list[rules.SessionLegEvidence], n_failed: int) -> list[dict[str, Any]]:
    """Every flag of one patient, most severe first (windows ending at ``now``)."""
    flags: list[dict[str, Any]] = []
    silent = rules.silent_flag(p, now, last, created, prescribed)
    if silent:
        flags.append(silent)
    for leg in assessed_legs(affected, list(series.get(metric.name, {}))):
        f = leg_flag(p, metric, series, leg)
        if f:
            flags.append(f)
    trouble = rules.sensor_flag(p, sensor_rows, n_failed)
    if trouble:
        flags.append(trouble)
    return _ranked(flags)


def _render(page: list[dict[str, Any]], now: datetime) -> None:
    """Only the returned page is rendered in full (windows as JSON, times as ISO strings)."""
    for it in page:
        it["last_session_at"] = it["last_session_at"].isoformat() if it["last_session_at"] else None
        for f in it["flags"]:
            for key in ("baseline", "latest"):
                if isinstance(f.get(key), stats.Window):
                    f[key] = rules.window_json(f[key], now)


def rules_block(p: AttentionParams, metric: Metric) -> dict[str, Any]:
    """What each flag means, with the thresholds of this response (the clinic's preset and overrides)."""
    trend_days = 2.0 * p.window_days
    goal = p.goal()
    companion = rules.LEVEL_FREE_COMPANION.get(metric.name) if p.level_free_test else None
    return {
        "preset": p.preset, "metric": metric.name, "activity": str(p.activity),
        "declining": {
            "severity": rules.SEVERITY["declining"],
            "method": (f"OLS slope of session means of the last {trend_days:g} days (>= {p.min_trend_sessions} "
                       f"sessions over >= {p.min_trend_span_days:g} days): one-sided t-test, alpha {p.alpha:g}"
                       + (f" (tested on {companion} of the same strides, free of the session's level offset)"
                          if companion else "")
                       + (f", its residual variance pooled with the pipeline's session scatter (sd "
                          f"{SESSION_SD_PRIOR.get(companion or metric.name):g}) as {p.sd_prior_df} df"
                          if p.sd_prior_df > 0 and SESSION_SD_PRIOR.get(companion or metric.name) else "")
                       + f", AND the metric's fitted change beyond the MDC ({metric.mdc:g} {metric.unit})"),
            "nominal_false_alarm_rate": p.alpha,
            "references": ["Montgomery & Runger, Applied Statistics, eq. 11-21", "Allseits et al. 2018 (MDC)",
                           "Smyth 2004, Stat Appl Genet Mol Biol 3(1):3 (moderated t)"]},
        "improving": {"severity": rules.SEVERITY["improving"], "method": "the declining rule in the better direction",
                      "nominal_false_alarm_rate": p.alpha},
        "stalled": {
            "severity": rules.SEVERITY["stalled"],
            "method": (f">= {max(p.min_trend_sessions, p.stalled_min_sessions)} sessions over >= "
                       f"{p.stalled_min_span_days:g} days in the last {p.stalled_weeks} weeks, both one-sided "
                       f"{100 * p.stalled_confidence:g} % bounds of the slope inside +-MDC per "
                       f"{p.stalled_margin_days:g} days (two one-sided tests), latest {p.window_days:g}-day mean "
                       f"below the goal, no significant improvement"),
            "goal": goal, "references": ["Schuirmann 1987 (two one-sided tests)",
                                         "Wellek 2010, Testing Statistical Hypotheses of Equivalence and "
                                         "Noninferiority, ch. 2"]},
        "silent": {"severity": rules.SEVERITY["silent"],
                   "method": (f"no session for {p.silent_missed_sessions:g} prescribed intervals (7 / prescribed "
                              f"sessions per week) when a schedule is set, else {p.silent_days:g} days")},
        "sensor_trouble": {
            "severity": rules.SEVERITY["sensor_trouble"],
            "method": (f"per leg over the last {p.window_days:g} days, after {p.min_strides_for_rates} expected "
                       f"strides: lost > {p.max_lost_rate:g}, low quality > {p.max_low_quality_rate:g}, fallback > "
                       f"{p.max_fallback_rate:g}, implausible angle > {p.max_implausible_rate:g}; per session: a "
                       f"sensor covering < {p.min_coverage:g} of it that cost >= {p.min_lost_strides} strides; "
                       f"> {p.max_failed_sessions} failed runs. Data gaps that cost no strides never count")},
        "ranking": "severity, then effect size (how far past its threshold the evidence is), most first",
    }


def attention_list(db: DbSession, *, clinician_id: str | None, params: AttentionParams | None = None,
                   now: datetime | None = None, limit: int = 50, offset: int = 0, live: bool = False) -> dict[str, Any]:
    """Flagged patients, most severe first. ``clinician_id`` None = every patient (admin).

    A preset's thresholds (``silent`` may be overridden) read the precomputed evidence: trend and sensor flags as of
    each patient's latest processed session. Other parameters, or ``live``, compute every flag with windows ending
    ``now``."""
    p = params or AttentionParams()
    metric = METRICS[p.metric]
    now = as_utc(now or utcnow())
    owned = [Patient.clinician_id == clinician_id] if clinician_id is not None else []
    if not live and precomputed_preset(p) is not None:
        return _from_evidence(db, p, metric, now, owned, limit, offset)
    patients = db.execute(
        select(Patient.id, Patient.display_name, Patient.external_id, Patient.affected_leg, Patient.created_at,
               Patient.prescribed_sessions_per_week).where(*owned).order_by(Patient.id)
    ).all()
    last_session = dict(db.execute(
        select(Session.patient_id, func.max(Session.started_at)).join(Patient, Patient.id == Session.patient_id)
        .where(*owned).group_by(Session.patient_id)
    ).all())
    horizon_days = max(2.0 * p.window_days, 7.0 * p.stalled_weeks)
    companion = rules.LEVEL_FREE_COMPANION.get(metric.name) if p.level_free_test else None
    points = _points(db, owned, [metric.name, *([companion] if companion else [])], p.activity,
                     now - timedelta(days=horizon_days), now)
    sensor_since = now - timedelta(days=p.window_days)
    sensor = _sensor_rows(db, owned, sensor_since)
    failed = dict(db.execute(
        select(Session.patient_id, func.count()).join(Patient, Patient.id == Session.patient_id)
        .where(*owned, Session.status == SessionStatus.failed, Session.started_at >= sensor_since)
        .group_by(Session.patient_id)
    ).all())

    items = []
    for pid, name, ext, affected, created, prescribed in patients:
        last = last_session.get(pid)
        flags = patient_flags(p, metric, now, points.get(pid, {}), affected, last, created, prescribed,
                              sensor.get(pid, []), int(failed.get(pid, 0)))
        if flags:
            items.append(_item(pid, name, ext, affected, prescribed, last, flags))
    return _page(items, p, metric, now, len(patients), limit, offset)


def _item(pid: str, name: str | None, ext: str | None, affected: str | None, prescribed: float | None,
          last: datetime | None, flags: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "patient": {"id": pid, "display_name": name, "external_id": ext, "affected_leg": affected,
                    "prescribed_sessions_per_week": prescribed},
        "severity": flags[0]["severity"], "effect": flags[0].get("effect"), "flags": flags,
        "last_session_at": as_utc(last) if last else None,
    }


def _page(items: list[dict[str, Any]], p: AttentionParams, metric: Metric, now: datetime, n_patients: int,
          limit: int, offset: int) -> dict[str, Any]:
    items.sort(key=lambda it: (-it["severity"], -(it["effect"] or 0.0), it["patient"]["id"]))
    page = items[offset:offset + limit]
    _render(page, now)
    return {
        "items": page, "next_cursor": str(offset + limit) if offset + limit < len(items) else None,
        "n_flagged": len(items), "n_patients": n_patients, "generated_at": now.isoformat(),
        "params": p.as_dict(), "rules": rules_block(p, metric),
    }


def precomputed_preset(p: AttentionParams) -> str | None:
    """The preset whose precomputed evidence answers ``p`` (only the silent limits may differ), else None."""
    preset = PRESETS.get(p.preset)
    if preset is None:
        return None
    same = replace(p, silent_days=preset.silent_days, silent_missed_sessions=preset.silent_missed_sessions)
    return p.preset if same == preset else None


_PENDING = (SessionStatus.receiving, SessionStatus.queued, SessionStatus.processing)


def _quiet_limit_days(p: AttentionParams, prescribed: float | None) -> float:
    """The silent limit of one patient in days (the rule of :func:`rules.silent_flag`)."""
    return p.silent_missed_sessions * 7.0 / prescribed if prescribed else p.silent_days


def _from_evidence(db: DbSession, p: AttentionParams, metric: Metric, now: datetime, owned: list[Any], limit: int,
                   offset: int) -> dict[str, Any]:
    """The list from each patient's attention row: one indexed query (patients of the clinician, their rows), the
    sessions still pending (the status index; usually none), ranking; only the returned page is decoded."""
    ae = AttentionEvidence
    # quiet_since: the latest processed session, else enrolment (one timestamp to parse per patient).
    rows = db.execute(
        select(Patient.id, Patient.affected_leg, func.coalesce(ae.as_of, Patient.created_at),
               Patient.prescribed_sessions_per_week, ae.legs, ae.flag_index)
        .outerjoin(ae, ae.patient_id == Patient.id).where(*owned)).all()
    pending = dict(db.execute(
        select(Session.patient_id, func.max(Session.started_at)).join(Patient, Patient.id == Session.patient_id)
        .where(*owned, Session.status.in_(_PENDING)).group_by(Session.patient_id)).all())
    now_s = now.timestamp()
    silent_sev = float(rules.SEVERITY["silent"])
    ranked = []  # (-severity, -effect, pid) without decoding any flag
    legs_of: dict[str, list[str]] = {}
    last_of: dict[str, datetime | None] = {}
    prefix = p.preset + "|"
    for pid, affected, quiet_since, prescribed, legs, index in rows:
        last = quiet_since if legs is not None else None  # legs is NOT NULL on a row: the patient has one
        if pid in pending and (last is None or as_utc(pending[pid]) > as_utc(last)):
            last = pending[pid]
        quiet_days = (now_s - as_utc(last if last is not None else quiet_since).timestamp()) / 86400.0
        limit_days = _quiet_limit_days(p, prescribed)
        tops = [(silent_sev, quiet_days / limit_days)] if quiet_days >= limit_days else []
        keys = []
        if index:
            assessed = set(assessed_legs(affected, legs.split(",") if legs else []))
            for entry in index.split(";"):
                if entry.startswith(prefix):
                    _, leg, _kind, sev, eff = entry.split("|")
                    if leg == "*" or leg in assessed:
                        keys.append(leg)
                        tops.append((float(sev), float(eff)))
        if not tops:
            continue
        sev, eff = max(tops)
        ranked.append((-sev, -round(eff, 3), pid))
        legs_of[pid] = keys
        last_of[pid] = last
    ranked.sort()
    page_ids = [pid for _, _, pid in ranked[offset:offset + limit]]
    items = []
    if page_ids:
        found = {r[0]: r for r in db.execute(
            select(Patient.id, Patient.display_name, Patient.external_id, Patient.affected_leg, Patient.created_at,
                   Patient.prescribed_sessions_per_week, ae.flags)
            .outerjoin(ae, ae.patient_id == Patient.id).where(Patient.id.in_(page_ids)))}
        for pid in page_ids:
            _, name, ext, affected, created, prescribed, doc = found[pid]
            last = last_of[pid]
            mine = json.loads(doc).get(p.preset, {}) if doc else {}
            silent = rules.silent_flag(p, now, last, created, prescribed)
            flags = [silent] if silent else []
            flags += [mine["sensor"] if leg == "*" else mine["legs"][leg] for leg in legs_of[pid]]
            items.append(_item(pid, name, ext, affected, prescribed, last, _ranked(flags)))
    out = _page(items, p, metric, now, len(rows), limit, 0)
    out["n_flagged"] = len(ranked)
    out["next_cursor"] = str(offset + limit) if offset + limit < len(ranked) else None
    return out


def evidence_document(db: DbSession, patient_id: str) -> tuple[datetime, dict[str, Any]] | None:
    """Every preset's trend and sensor flags of one patient with windows ending at their latest processed session
    (None without one)."""
    as_of = db.scalar(select(func.max(Session.started_at)).where(
        Session.patient_id == patient_id, Session.status.in_([SessionStatus.done, SessionStatus.failed])))
    if as_of is None:
        return None
    as_of = as_utc(as_of)
    owned = [Patient.id == patient_id]
    doc: dict[str, Any] = {"as_of": as_of.isoformat(), "legs": [], "presets": {}}
    for name, p in PRESETS.items():
        metric = METRICS[p.metric]
        companion = rules.LEVEL_FREE_COMPANION.get(metric.name) if p.level_free_test else None
        horizon = timedelta(days=max(2.0 * p.window_days, 7.0 * p.stalled_weeks))
        series = _points(db, owned, [metric.name, *([companion] if companion else [])], p.activity,
                         as_of - horizon, as_of).get(patient_id, {})
        since = as_of - timedelta(days=p.window_days)
        n_failed = db.scalar(select(func.count()).select_from(Session).where(
            Session.patient_id == patient_id, Session.status == SessionStatus.failed, Session.started_at >= since))
        legs = sorted(series.get(metric.name, {}))
        doc["legs"] = legs
        per_leg = {leg: leg_flag(p, metric, series, leg) for leg in legs}
        sensor = rules.sensor_flag(p, _sensor_rows(db, owned, since).get(patient_id, []), int(n_failed or 0))
        if sensor:
            sensor["severity"] = rules.SEVERITY["sensor_trouble"]
        rendered = [{"flags": [f for f in [*per_leg.values(), sensor] if f], "last_session_at": None}]
        _render(rendered, as_of)
        doc["presets"][name] = {"legs": per_leg, "sensor": sensor}
    return as_of, doc
