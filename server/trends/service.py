"""Trend, symmetry and completeness views of one patient, computed from the per-session-leg summaries.

Method (also in the README):
- Buckets: local days or ISO weeks (Monday start) in the patient's time zone; a session belongs to the local day
  of its start. Bucket statistics pool the included strides of all sessions in the bucket
  (``strides_per_day``: the per-day totals of trustworthy strides of the leg, over days with data).
- Trend: slope per week over SESSION-level values (the mean of each session's included strides; sessions with fewer
  than ``MIN_STRIDES_PER_SESSION`` included strides are left out), time = session start. ``method=ols`` (default):
  least squares with a t-based 95 % CI; ``method=theil_sen``: median of pairwise slopes with Sen's CI.
  ``strides_per_day`` uses one point per local day.
- Change: baseline window (first ``window_days`` from the first session in range) vs latest window (last
  ``window_days`` up to the last session), see :func:`server.trends.stats.change` for the significance rule.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from datetime import UTC, date, datetime, timedelta
from typing import Any

import numpy as np
from sqlalchemy import and_, func, select
from sqlalchemy.orm import Session as DbSession

from server.codec import decode_values
from server.enums import SessionStatus, StrideActivity
from server.numbers import finite_round
from server.patients.models import Patient
from server.sessions.models import Batch, Session
from server.trends import stats
from server.trends.metrics import METRICS, MIN_QUALITY, MIN_STRIDES_PER_SESSION, Metric
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.timeutil import Bucket, bucket_bounds, bucket_date, local_date, local_midnight, zone
from server.utc import as_utc, utcnow

WINDOW_DAYS = 14.0
MIN_WINDOW_STRIDES = 20
MIN_WINDOW_DAYS = 3  # count metrics: days with data per change window


def _iso(dt: datetime | None) -> str | None:
    return None if dt is None else dt.isoformat()


@dataclass
class SessionRow:
    """One session's summary of one metric, leg and activity."""

    session_id: str
    started_at: datetime  # aware UTC
    n_included: int
    n_excluded: int
    n_low_quality: int
    n_implausible: int
    mean: float | None
    sd: float | None
    median: float | None = None
    p10: float | None = None
    p90: float | None = None
    values: bytes | None = None
    activity: str = StrideActivity.walking


def _time_filter(col: Any, start: datetime | None, end: datetime | None) -> list[Any]:
    conds = []
    if start is not None:
        conds.append(col >= start.astimezone(UTC))
    if end is not None:
        conds.append(col < end.astimezone(UTC))
    return conds


def legs_with_data(db: DbSession, patient_id: str, activity: str = StrideActivity.walking) -> list[str]:
    """Legs with at least one stride of the activity, most strides first."""
    rows = db.execute(
        select(TrendSessionLeg.leg, func.sum(TrendSessionLeg.n_strides))
        .where(TrendSessionLeg.patient_id == patient_id, TrendSessionLeg.activity == activity)
        .group_by(TrendSessionLeg.leg)
    ).all()
    return [leg for leg, n in sorted(rows, key=lambda r: -(r[1] or 0)) if (n or 0) > 0]


def summaries_version(db: DbSession, patient_id: str) -> tuple[int, str]:
    """What changes whenever a patient's trend summaries do: every processing run rewrites its session's legs with
    a new ``refreshed_at``, and a deleted session removes them (their count and newest refresh time)."""
    n, last = db.execute(select(func.count(), func.max(TrendSessionLeg.refreshed_at))
                         .where(TrendSessionLeg.patient_id == patient_id)).one()
    return int(n), str(last)


def default_leg(db: DbSession, patient: Patient, activity: str = StrideActivity.walking) -> str | None:
    """The affected leg when it has data (or nothing has), else the leg with the most strides."""
    legs = legs_with_data(db, patient.id, activity)
    if patient.affected_leg and (patient.affected_leg in legs or not legs):
        return patient.affected_leg
    return legs[0] if legs else None


def latest_session_means(db: DbSession, patient_ids: list[str], metrics: tuple[str, ...],
                         activity: str = StrideActivity.walking
                         ) -> dict[str, dict[str, dict[str, dict[str, Any]]]]:
    """{patient: {leg: {metric: {mean, at}}}}: per patient, leg and metric, the mean of the included strides of one
    activity in the most recent session that has any, in one query for a list of patients (read along the
    summaries' (patient, metric, leg, activity, time) index). Activities are never pooled, as in the trends."""
    if not patient_ids:
        return {}
    m = TrendMetricValues
    last = (select(m.patient_id, m.metric, m.leg, func.max(m.started_at).label("t"))
            .where(m.patient_id.in_(patient_ids), m.metric.in_(metrics), m.activity == activity,
                   m.n_included > 0)
            .group_by(m.patient_id, m.metric, m.leg).subquery())
    rows = db.execute(select(m.patient_id, m.leg, m.metric, m.mean, m.started_at).join(
        last, (last.c.patient_id == m.patient_id) & (last.c.metric == m.metric) & (last.c.leg == m.leg)
        & (last.c.t == m.started_at)).where(m.activity == activity, m.n_included > 0)).all()
    out: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for pid, leg, metric, mean, at in rows:
        if mean is not None:
            out.setdefault(pid, {}).setdefault(leg, {})[metric] = {"mean": float(mean), "at": as_utc(at)}
    return out


def session_medians(db: DbSession, session_ids: list[str], metric_name: str
                    ) -> dict[str, dict[str, tuple[int, float | None]]]:
    """{session: {leg: (included strides, their median)}} of one metric from the trend summaries (so a stride that
    does not count in the trends does not count here either). A session holding both activities (uploaded as
    ``unknown``) gives its walking strides' figures: activities are never pooled, and walking is what the
    clinician's trends show first."""
    m = TrendMetricValues
    out: dict[str, dict[str, tuple[int, float | None]]] = {}
    if not session_ids:
        return out
    rows = db.execute(select(m.session_id, m.leg, m.activity, m.n_included, m.median).where(
        m.session_id.in_(session_ids), m.metric == metric_name)).all()
    for sid, leg, _, n, median in sorted(rows, key=lambda r: r[2] == StrideActivity.walking):
        out.setdefault(sid, {})[leg] = (int(n), None if median is None else float(median))
    return out


def load_session_rows(db: DbSession, patient_id: str, metric: Metric, leg: str, start: datetime | None,
                      end: datetime | None, activity: str = StrideActivity.walking) -> list[SessionRow]:
    """The session summaries of one metric and leg in time order, without value arrays (see :func:`attach_values`)."""
    if metric.column is None:  # count metric: from the session-leg counts
        q = (select(TrendSessionLeg.session_id, TrendSessionLeg.started_at, TrendSessionLeg.n_strides,
                    TrendSessionLeg.n_low_quality)
             .where(TrendSessionLeg.patient_id == patient_id, TrendSessionLeg.leg == leg,
                    TrendSessionLeg.activity == activity,
                    *_time_filter(TrendSessionLeg.started_at, start, end))
             .order_by(TrendSessionLeg.started_at))
        out = []
        for sid, t, n, low in db.execute(q):
            ok = (n or 0) - (low or 0)
            out.append(SessionRow(sid, as_utc(t), ok, low or 0, low or 0, 0, float(ok), None, activity=activity))
        return out
    m, s = TrendMetricValues, TrendSessionLeg
    q = (select(m.session_id, m.started_at, m.n_included, m.n_implausible, m.mean, m.sd, m.median, m.p10, m.p90,
                s.n_low_quality)
         .join(s, and_(s.session_id == m.session_id, s.leg == m.leg, s.activity == m.activity))
         .where(m.patient_id == patient_id, m.metric == metric.name, m.leg == leg, m.activity == activity,
                *_time_filter(m.started_at, start, end))
         .order_by(m.started_at))
    out = []
    for sid, t, n, n_impl, mean, sd, med, p10, p90, low in db.execute(q):
        low = low or 0
        out.append(SessionRow(sid, as_utc(t), n, low + n_impl, low, n_impl, mean, sd, med, p10, p90,
                              activity=activity))
    return out


def attach_values(db: DbSession, metric: Metric, leg: str, rows: list[SessionRow]) -> None:
    """Load the value arrays of these rows (only buckets pooling several sessions need them: the arrays are the
    bulk of the bytes, ~4 kB per 1,000 strides)."""
    ids = [r.session_id for r in rows if r.values is None and r.n_included]
    blobs: dict[tuple[str, str], bytes] = {}
    m = TrendMetricValues
    activities = sorted({r.activity for r in rows})
    for i in range(0, len(ids), 500):
        for sid, act, blob in db.execute(select(m.session_id, m.activity, m.values).where(
                m.session_id.in_(ids[i:i + 500]), m.metric == metric.name, m.leg == leg,
                m.activity.in_(activities))):
            blobs[(sid, act)] = blob
    for r in rows:
        if r.values is None:
            r.values = blobs.get((r.session_id, r.activity), b"")


def _describe_rows(rows: list[SessionRow]) -> stats.Describe:
    """Bucket statistics from the session summaries: mean and sd pooled exactly from the stored per-session
    n/mean/sd; quantiles stored per session (one-session bucket) or from the merged ascending value arrays."""
    n, mean, sd = stats.pool([stats.Point(0.0, r.n_included, r.mean, r.sd) for r in rows if r.n_included])
    if n == 0:
        return stats.Describe(0, None, None, None, None, None, None)
    cv = sd / mean if sd is not None and mean else None
    used = [r for r in rows if r.n_included]
    if len(used) == 1 and used[0].p10 is not None:
        r = used[0]
        return stats.Describe(n, mean, sd, r.median, r.p10, r.p90, cv)
    v = np.sort(decode_values(b"".join(r.values or b"" for r in used)))
    p10, median, p90 = stats.quantiles_sorted(v, (0.1, 0.5, 0.9))
    return stats.Describe(n, mean, sd, median, p10, p90, cv)


def _needs_values(rows: list[SessionRow]) -> bool:
    used = [r for r in rows if r.n_included]
    return len(used) > 1 or (len(used) == 1 and used[0].p10 is None)


def _bucket_stats(db: DbSession, metric: Metric, leg: str, rows: list[SessionRow], bucket: Bucket,
                  tz: Any) -> list[dict[str, Any]]:
    # Rows come ordered by time, so each bucket's rows (and their values) are one contiguous run.
    groups: dict[date, list[SessionRow]] = {}
    for r in rows:
        groups.setdefault(bucket_date(local_date(r.started_at, tz), bucket), []).append(r)
    keys = sorted(groups)
    if metric.column is None:
        # Per-day totals inside the bucket (a week has up to seven of them).
        chunks = []
        for key in keys:
            per_day: dict[date, float] = defaultdict(float)
            for r in groups[key]:
                per_day[local_date(r.started_at, tz)] += r.n_included
            chunks.append(np.fromiter(per_day.values(), dtype=np.float64))
        lengths = np.array([c.size for c in chunks])
        values = np.concatenate(chunks) if chunks else np.empty(0)
        described = stats.describe_segments(values, lengths)
    else:
        attach_values(db, metric, leg, [r for key in keys if _needs_values(groups[key]) for r in groups[key]])
        described = [_describe_rows(groups[key]) for key in keys]
    out = []
    for key, d in zip(keys, described, strict=True):
        grp = groups[key]
        b0, b1 = bucket_bounds(key, bucket, tz)
        out.append({
            "start": b0.isoformat(), "end": b1.isoformat(),
            "n_sessions": len({r.session_id for r in grp}),
            "n_strides": int(sum(r.n_included for r in grp)),
            "n_excluded": int(sum(r.n_excluded for r in grp)),
            "mean": finite_round(d.mean), "sd": finite_round(d.sd), "median": finite_round(d.median),
            "p10": finite_round(d.p10), "p90": finite_round(d.p90),
            "cv": finite_round(d.cv), "n_values": d.n,
        })
    return out


def session_points(metric: Metric, rows: list[SessionRow], tz: Any) -> tuple[list[stats.Point], datetime | None]:
    """Session-level (count metrics: day-level) points; t in days since the first point's time."""
    if not rows:
        return [], None
    if metric.column is None:
        per_day: dict[date, int] = defaultdict(int)
        for r in rows:
            per_day[local_date(r.started_at, tz)] += r.n_included
        days = sorted(per_day)
        t0 = local_midnight(days[0], tz).astimezone(UTC)
        return [stats.Point(float((d - days[0]).days), 1, float(per_day[d]), None) for d in days], t0
    kept = [r for r in rows if r.n_included >= MIN_STRIDES_PER_SESSION and r.mean is not None]
    if not kept:
        return [], None
    t0 = kept[0].started_at
    return [stats.Point((r.started_at - t0).total_seconds() / 86400.0, r.n_included, float(r.mean),
                        r.sd) for r in kept], t0


def _window_out(w: stats.Window | None, t0: datetime | None) -> dict[str, Any] | None:
    if w is None or t0 is None:
        return None
    return {
        "start": _iso(t0 + timedelta(days=w.start_days)), "end": _iso(t0 + timedelta(days=w.end_days)),
        "n_sessions": w.n_sessions, "n": w.n, "mean": finite_round(w.mean), "sd": finite_round(w.sd),
        "ci95": None if w.ci95 is None else [finite_round(w.ci95[0]), finite_round(w.ci95[1])], "ci_basis": w.ci_basis,
    }


def direction(metric: Metric, ch: stats.Change) -> str | None:
    """improved | declined | changed (no better direction) | unchanged (not significant) | None (no data)."""
    if ch.delta is None:
        return None
    if not ch.significant:
        return "unchanged"
    if metric.better == "none":
        return "changed"
    up = ch.delta > 0
    return "improved" if up == (metric.better == "higher") else "declined"


def change_out(metric: Metric, points: list[stats.Point], t0: datetime | None,
               window_days: float = WINDOW_DAYS) -> dict[str, Any]:
    """The baseline vs latest window change of a metric, as JSON."""
    min_n = MIN_WINDOW_DAYS if metric.column is None else MIN_WINDOW_STRIDES
    ch = stats.change(points, mdc=metric.mdc, mdc_relative=metric.mdc_relative, window_days=window_days,
                      min_n=min_n)
    return {
        "baseline": finite_round(ch.baseline.mean) if ch.baseline else None,
        "latest": finite_round(ch.latest.mean) if ch.latest else None,
        "delta": finite_round(ch.delta), "mdc": finite_round(ch.mdc), "significant": ch.significant,
        "direction": direction(metric, ch),
        "baseline_window": _window_out(ch.baseline, t0), "latest_window": _window_out(ch.latest, t0),
        "window_days": window_days, "reasons": ch.reasons,
    }


def trend_out(points: list[stats.Point], method: stats.SlopeMethod) -> dict[str, Any]:
    """The slope per week with its CI, as JSON."""
    sl = stats.slope(np.array([p.t_days for p in points]), np.array([p.mean for p in points]), method)
    per_week, ci = sl.per_week()
    return {
        "slope_per_week": finite_round(per_week, 6),
        "ci95": [finite_round(ci[0], 6), finite_round(ci[1], 6)] if ci else [None, None],
        "n": sl.n, "method": method, "p_value": finite_round(sl.p_value, 6),
        "basis": "days" if len(points) and points[0].n == 1 and points[0].sd is None else "sessions",
    }


def patient_trends(db: DbSession, patient: Patient, *, metric_name: str, leg: str | None, bucket: Bucket,
                   start: datetime | None, end: datetime | None, method: stats.SlopeMethod = "ols",
                   window_days: float = WINDOW_DAYS, activity: str = StrideActivity.walking) -> dict[str, Any]:
    """Buckets, slope and change of one metric of one leg and activity (walking and running are never pooled)."""
    metric = METRICS[metric_name]
    tz = zone(patient.timezone)
    leg = leg or default_leg(db, patient, activity)
    rows = load_session_rows(db, patient.id, metric, leg, start, end, activity) if leg else []
    buckets = _bucket_stats(db, metric, leg, rows, bucket, tz)
    points, t0 = session_points(metric, rows, tz)
    trend_basis_unit = "per local day" if metric.column is None else "per session"
    return {
        "patient_id": patient.id, "metric": metric.name, "unit": metric.unit, "leg": leg, "bucket": bucket,
        "activity": str(activity), "timezone": tz.key, "from": _iso(start), "to": _iso(end),
        "buckets": buckets,
        "trend": trend_out(points, method),
        "change": change_out(metric, points, t0, window_days),
        "excluded": {
            "n_low_quality": int(sum(r.n_low_quality for r in rows)),
            "n_implausible": int(sum(r.n_implausible for r in rows)),
        },
        "rules": {
            "min_quality": MIN_QUALITY, "plausible_range": [metric.lo, metric.hi if np.isfinite(metric.hi) else None],
            "min_strides_per_session": MIN_STRIDES_PER_SESSION, "trend_points": trend_basis_unit,
            "better": metric.better,
        },
    }


def patient_symmetry(db: DbSession, patient: Patient, *, metric_name: str, bucket: Bucket,
                     start: datetime | None, end: datetime | None,
                     activity: str = StrideActivity.walking) -> dict[str, Any]:
    """Affected vs other leg per bucket: ratio of bucket means and the symmetry index
    SI = 100 * (affected - other) / (0.5 * (affected + other)) (Robinson, Herzog & Nigg 1987, J Manipulative Physiol
    Ther 10:172). SI 0 is perfect symmetry; negative means the affected leg reaches less. Without a recorded
    affected leg the left leg is the reference (``affected_leg`` null in the response)."""
    metric = METRICS[metric_name]
    tz = zone(patient.timezone)
    ref = patient.affected_leg or "left"
    other = "right" if ref == "left" else "left"
    by_leg = {leg: {b["start"]: b for b in _bucket_stats(db, metric, leg, load_session_rows(
        db, patient.id, metric, leg, start, end, activity), bucket, tz)} for leg in (ref, other)}
    out = []
    for key in sorted(set(by_leg[ref]) | set(by_leg[other])):
        a, o = by_leg[ref].get(key), by_leg[other].get(key)
        am, om = (a or {}).get("mean"), (o or {}).get("mean")
        ratio = si = None
        if am is not None and om is not None:
            ratio = am / om if om != 0 else None
            si = 100.0 * (am - om) / (0.5 * (am + om)) if (am + om) != 0 else None
        out.append({
            "start": key, "reference": {"n_strides": (a or {}).get("n_strides", 0), "mean": am},
            "other": {"n_strides": (o or {}).get("n_strides", 0), "mean": om},
            "ratio": finite_round(ratio), "symmetry_index_pct": finite_round(si, 2),
        })
    return {"patient_id": patient.id, "metric": metric.name, "unit": metric.unit, "bucket": bucket,
            "activity": str(activity), "affected_leg": patient.affected_leg, "reference_leg": ref,
            "other_leg": other, "timezone": tz.key,
            "from": _iso(start), "to": _iso(end), "buckets": out}


def patient_completeness(db: DbSession, patient: Patient, *, days: int = 30, now: datetime | None = None,
                         activity: str = StrideActivity.walking) -> dict[str, Any]:
    """The remote-monitoring view: which of the last ``days`` local days have data, strides and walking minutes.

    A session's strides/walking time is that of its busiest leg (both legs walk the same cycles; adding them would
    double-count); strides and time count only the given activity. ``n_sessions`` counts every session started
    that day, processed or not.
    """
    tz = zone(patient.timezone)
    now = as_utc(now or utcnow())
    today = now.astimezone(tz).date()
    first = today - timedelta(days=days - 1)
    start = local_midnight(first, tz).astimezone(UTC)
    end = local_midnight(today + timedelta(days=1), tz).astimezone(UTC)
    sessions = db.execute(
        select(Session.id, Session.started_at, Session.status)
        .where(Session.patient_id == patient.id, *_time_filter(Session.started_at, start, end))
    ).all()
    legs = db.execute(
        select(TrendSessionLeg.session_id, TrendSessionLeg.n_strides, TrendSessionLeg.n_low_quality,
               TrendSessionLeg.walking_s)
        .where(TrendSessionLeg.patient_id == patient.id, TrendSessionLeg.activity == activity,
               *_time_filter(TrendSessionLeg.started_at, start, end))
    ).all()
    per_session: dict[str, tuple[int, int, float]] = {}
    for sid, n, low, walk in legs:
        prev = per_session.get(sid, (0, 0, 0.0))
        per_session[sid] = (max(prev[0], n - low), max(prev[1], n), max(prev[2], walk or 0.0))
    day_rows: dict[date, dict[str, Any]] = {
        first + timedelta(days=i): {"n_sessions": 0, "n_failed": 0, "n_strides": 0, "n_strides_all": 0,
                                    "walking_s": 0.0} for i in range(days)}
    for sid, started, status in sessions:
        d = day_rows.get(local_date(started, tz))
        if d is None:
            continue
        d["n_sessions"] += 1
        d["n_failed"] += status == SessionStatus.failed
        ok, n_all, walk = per_session.get(sid, (0, 0, 0.0))
        d["n_strides"] += ok
        d["n_strides_all"] += n_all
        d["walking_s"] += walk
    last_upload = db.scalar(select(func.max(Batch.created_at)).join(Session, Session.id == Batch.session_id)
                            .where(Session.patient_id == patient.id))
    last_session = db.scalar(select(func.max(Session.started_at)).where(Session.patient_id == patient.id))
    out_days = [{"date": d.isoformat(), "n_sessions": v["n_sessions"], "n_failed": v["n_failed"],
                 "n_strides": v["n_strides"], "n_strides_all": v["n_strides_all"],
                 "walking_min": round(v["walking_s"] / 60.0, 2)} for d, v in sorted(day_rows.items())]
    return {
        "patient_id": patient.id, "activity": str(activity), "timezone": tz.key, "days": days,
        "from": first.isoformat(), "to": today.isoformat(),
        "days_with_data": sum(1 for v in day_rows.values() if v["n_strides"] > 0),
        "days_with_sessions": sum(1 for v in day_rows.values() if v["n_sessions"] > 0),
        "strides_total": sum(v["n_strides"] for v in day_rows.values()),
        "walking_min_total": round(sum(v["walking_s"] for v in day_rows.values()) / 60.0, 2),
        "last_upload_at": _iso(as_utc(last_upload)) if last_upload else None,
        "last_session_at": _iso(as_utc(last_session)) if last_session else None,
        "per_day": out_days,
    }
