"""The attention list: which patients need the clinician this week, with the reason and the numbers behind it.

Flags (severity 3 = act now ... 1 = review):
- ``declining`` (3): peak swing flexion (or ``metric``) of the assessed leg got significantly worse: latest window
  [now - window_days, now] vs the window before it, same significance rule as the trends ``change``
  (|delta| > MDC, enough strides, non-overlapping 95 % CIs; :func:`server.trends.stats.compare`).
- ``sensor_trouble`` (2): in the latest window, more than ``max_fallback_rate`` of the strides are fallbacks (the
  pipeline could not use its activity's primary estimator on them, e.g. the complementary filter instead of the
  gyroscope-only estimator when walking), or more than ``max_gaps_per_hour``
  data gaps per walking hour; failed processing runs are reported alongside.
- ``silent`` (2): no session for >= ``silent_days`` days (or none since enrolment that long ago).
- ``stalled`` (1): monitored for ``stalled_weeks`` weeks but no significant improvement: the latest window vs the
  window that starts ``stalled_weeks`` weeks ago.
Assessed leg: the affected leg when it has data, otherwise every leg with data.

All the heavy lifting is SQL aggregation over the summary tables (window moments per patient and leg), so the cost
grows with the number of patients, not with their strides.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import case, func, select
from sqlalchemy.orm import Session as DbSession

from server.enums import SessionStatus, StrideActivity
from server.numbers import finite_round
from server.patients.models import Patient
from server.sessions.models import Session
from server.trends import stats
from server.trends.metrics import METRICS, MIN_STRIDES_PER_SESSION, Metric
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.service import MIN_WINDOW_STRIDES
from server.utc import as_utc, utcnow

SEVERITY = {"declining": 3, "sensor_trouble": 2, "silent": 2, "stalled": 1}


@dataclass(frozen=True)
class AttentionParams:
    """The thresholds of the flags (also echoed in the response)."""

    metric: str = "peak_swing_flexion_deg"
    window_days: float = 14.0
    silent_days: float = 3.0
    stalled_weeks: int = 4
    max_fallback_rate: float = 0.3
    max_gaps_per_hour: float = 12.0
    min_strides_for_rates: int = 50  # fewer strides than this say nothing about a sensor
    activity: str = StrideActivity.walking  # declining/stalled compare strides of this activity only


def _interval_moments(db: DbSession, owned: list[Any], metric: str, edges: list[datetime],
                      activity: str) -> dict[str, dict]:
    """Session moments per patient, leg and elementary interval [edges[i], edges[i+1]).

    Windows are unions of these intervals and moments add up, so SQL evaluates one CASE and six sums per row
    however the windows overlap. Returns {patient_id: {leg: {i: (k, n, s1, s2, m1, m2)}}}."""
    m = TrendMetricValues
    idx = case(*[(m.started_at < edges[i + 1], i) for i in range(len(edges) - 1)], else_=-1)
    sd2 = func.coalesce(m.sd, 0.0) * func.coalesce(m.sd, 0.0)
    q = (select(m.patient_id, m.leg, idx, func.count(), func.sum(m.n_included), func.sum(m.n_included * m.mean),
                func.sum((m.n_included - 1) * sd2 + m.n_included * m.mean * m.mean), func.sum(m.mean),
                func.sum(m.mean * m.mean))
         .join(Patient, Patient.id == m.patient_id)
         .where(*owned, m.metric == metric, m.activity == activity, m.n_included >= MIN_STRIDES_PER_SESSION,
                m.started_at >= edges[0], m.started_at < edges[-1])
         .group_by(m.patient_id, m.leg, idx))
    out: dict[str, dict] = {}
    # Every group has >= 1 row with n_included >= 5, so no sum is NULL.
    for pid, leg, i, *mom in db.execute(q):
        out.setdefault(pid, {}).setdefault(leg, {})[i] = mom
    return out


def _window(per_interval: dict[int, tuple], idx: list[int], days: tuple[float, float]) -> stats.Window:
    """The window made of the elementary intervals ``idx`` (moments add up)."""
    k = n = s1 = s2 = m1 = m2 = 0.0
    for i in idx:
        mom = per_interval.get(i)
        if mom is not None:
            k, n, s1, s2, m1, m2 = k + mom[0], n + mom[1], s1 + mom[2], s2 + mom[3], m1 + mom[4], m2 + mom[5]
    return stats.window_from_moments(days[0], days[1], k=int(k), n=int(n), s1=s1, s2=s2, m1=m1, m2=m2)


def _win_json(w: stats.Window, now: datetime) -> dict[str, Any]:
    return {"start": (now + timedelta(days=w.start_days)).isoformat(),
            "end": (now + timedelta(days=w.end_days)).isoformat(), "n_sessions": w.n_sessions, "n_strides": w.n,
            "mean": finite_round(w.mean, 3),
            "ci95": None if w.ci95 is None else [finite_round(w.ci95[0], 3), finite_round(w.ci95[1], 3)]}


_Part = tuple[list[int], tuple[float, float]]


@dataclass(frozen=True)
class _Windows:
    """The elementary intervals and day offsets of the three comparison windows."""

    latest: _Part
    declining: _Part
    stalled: _Part


def _silent_flag(p: AttentionParams, now: datetime, last: datetime | None,
                 created: datetime) -> dict[str, Any] | None:
    quiet_since = last if last is not None else created
    quiet_days = (now - as_utc(quiet_since)).total_seconds() / 86400.0
    if quiet_days < p.silent_days:
        return None
    return {"kind": "silent", "days_without_data": finite_round(quiet_days, 1),
            "last_session_at": as_utc(last).isoformat() if last else None,
            "reason": (f"no session for {quiet_days:.1f} days" if last else
                       f"no session since enrolment {quiet_days:.1f} days ago")}


def _declining_flag(metric: Metric, leg: str, per_interval: dict[int, tuple],
                    windows: _Windows) -> dict[str, Any] | None:
    base = _window(per_interval, *windows.declining)
    latest = _window(per_interval, *windows.latest)
    ch = stats.compare(base, latest, mdc=metric.mdc, mdc_relative=metric.mdc_relative, min_n=MIN_WINDOW_STRIDES)
    worse = ch.delta is not None and (ch.delta < 0) == (metric.better == "higher")
    if not (ch.significant and worse and metric.better != "none"):
        return None
    return {"kind": "declining", "leg": leg, "metric": metric.name, "delta": finite_round(ch.delta, 3),
            "mdc": finite_round(ch.mdc, 3), "baseline": base, "latest": latest,
            "reason": (f"{metric.name} of the {leg} leg fell by {abs(ch.delta):.1f} {metric.unit} "
                       f"(MDC {ch.mdc:g}) from {base.mean:.1f} to {latest.mean:.1f}")}


def _stalled_flag(p: AttentionParams, metric: Metric, leg: str, per_interval: dict[int, tuple],
                  windows: _Windows) -> dict[str, Any] | None:
    sb = _window(per_interval, *windows.stalled)
    latest = _window(per_interval, *windows.latest)
    if sb.n_sessions == 0 or latest.n_sessions == 0:
        return None  # not monitored across the whole period
    ch = stats.compare(sb, latest, mdc=metric.mdc, mdc_relative=metric.mdc_relative, min_n=MIN_WINDOW_STRIDES)
    better = ch.delta is not None and (ch.delta > 0) == (metric.better == "higher")
    if ch.significant and better:
        return None
    return {"kind": "stalled", "leg": leg, "metric": metric.name, "weeks": p.stalled_weeks,
            "delta": finite_round(ch.delta, 3), "mdc": finite_round(ch.mdc, 3), "baseline": sb, "latest": latest,
            "reason": (f"no significant improvement of {metric.name} ({leg}) over "
                       f"{p.stalled_weeks} weeks: change {ch.delta:+.1f} {metric.unit}, "
                       f"MDC {ch.mdc:g}")}


def _sensor_flag(p: AttentionParams, counts: tuple | None, n_failed: int) -> dict[str, Any] | None:
    n_str, n_fb, n_gaps, walk_s = counts or (0, 0, 0, 0.0)
    n_str, n_fb, n_gaps, walk_s = int(n_str or 0), int(n_fb or 0), int(n_gaps or 0), float(walk_s or 0.0)
    fb_rate = n_fb / n_str if n_str else None
    gaps_h = n_gaps / (walk_s / 3600.0) if walk_s >= 60.0 else None
    trouble = []
    if n_str >= p.min_strides_for_rates and fb_rate is not None and fb_rate > p.max_fallback_rate:
        trouble.append(f"{100 * fb_rate:.0f} % of strides from the fallback estimator "
                       f"(limit {100 * p.max_fallback_rate:.0f} %)")
    if gaps_h is not None and n_str >= p.min_strides_for_rates and gaps_h > p.max_gaps_per_hour:
        trouble.append(f"{gaps_h:.1f} data gaps per walking hour (limit {p.max_gaps_per_hour:g})")
    if not trouble:
        return None
    return {"kind": "sensor_trouble", "fallback_rate": finite_round(fb_rate, 3),
            "gaps_per_walking_hour": finite_round(gaps_h, 3),
            "n_strides": n_str, "n_fallback": n_fb, "n_gaps": n_gaps,
            "walking_min": finite_round(walk_s / 60.0, 1), "failed_sessions": n_failed,
            "reason": "; ".join(trouble)}


def _patient_flags(p: AttentionParams, metric: Metric, now: datetime, windows: _Windows,
                   per_leg: dict[str, dict[int, tuple]], affected: str | None, last: datetime | None,
                   created: datetime, sensor_counts: tuple | None, n_failed: int) -> list[dict[str, Any]]:
    """Every flag of one patient, in the order silent, declining, stalled, sensor trouble."""
    silent = _silent_flag(p, now, last, created)
    flags: list[dict[str, Any]] = [silent] if silent else []
    legs = [affected] if affected in per_leg else sorted(per_leg)
    declining = {leg: _declining_flag(metric, leg, per_leg[leg], windows) for leg in legs}
    flags.extend(f for f in declining.values() if f)
    for leg in legs:
        if declining[leg] is None and (stalled := _stalled_flag(p, metric, leg, per_leg[leg], windows)):
            flags.append(stalled)
    trouble = _sensor_flag(p, sensor_counts, n_failed)
    if trouble:
        flags.append(trouble)
    return flags


def _render(page: list[dict[str, Any]], now: datetime) -> None:
    """Only the returned page is rendered in full (windows as JSON, times as ISO strings)."""
    for it in page:
        it["last_session_at"] = it["last_session_at"].isoformat() if it["last_session_at"] else None
        for f in it["flags"]:
            for key in ("baseline", "latest"):
                if isinstance(f.get(key), stats.Window):
                    f[key] = _win_json(f[key], now)


def attention_list(db: DbSession, *, clinician_id: str | None, params: AttentionParams | None = None,
                   now: datetime | None = None, limit: int = 50, offset: int = 0) -> dict[str, Any]:
    """Flagged patients, most severe first. ``clinician_id`` None = every patient (admin)."""
    p = params or AttentionParams()
    metric = METRICS[p.metric]
    now = as_utc(now or utcnow())
    win = timedelta(days=p.window_days)
    stall_start = now - timedelta(weeks=p.stalled_weeks)
    owned = [Patient.clinician_id == clinician_id] if clinician_id is not None else []

    patients = db.execute(
        select(Patient.id, Patient.display_name, Patient.external_id, Patient.affected_leg, Patient.created_at)
        .where(*owned).order_by(Patient.id)
    ).all()
    last_session = dict(db.execute(
        select(Session.patient_id, func.max(Session.started_at)).join(Patient, Patient.id == Session.patient_id)
        .where(*owned).group_by(Session.patient_id)
    ).all())

    # Windows: declining baseline, latest, stalled baseline (may coincide with or overlap the first).
    latest_w = (now - win, now + timedelta(seconds=1))
    decl_w = (now - 2 * win, now - win)
    stall_w = (stall_start, stall_start + win)
    edges = sorted({*latest_w, *decl_w, *stall_w})
    moments = _interval_moments(db, owned, metric.name, edges, p.activity)

    def parts(w: tuple[datetime, datetime]) -> tuple[list[int], tuple[float, float]]:
        idx = [i for i in range(len(edges) - 1) if edges[i] >= w[0] and edges[i + 1] <= w[1]]
        return idx, ((w[0] - now).total_seconds() / 86400.0, (w[1] - now).total_seconds() / 86400.0)

    windows = _Windows(latest=parts(latest_w), declining=parts(decl_w), stalled=parts(stall_w))

    s = TrendSessionLeg
    sensor = {r[0]: r[1:] for r in db.execute(
        select(s.patient_id, func.sum(s.n_strides), func.sum(s.n_fallback), func.sum(s.n_gaps),
               func.sum(s.walking_s)).join(Patient, Patient.id == s.patient_id)
        .where(*owned, s.started_at >= now - win).group_by(s.patient_id)
    ).all()}
    failed = dict(db.execute(
        select(Session.patient_id, func.count()).join(Patient, Patient.id == Session.patient_id)
        .where(*owned, Session.status == SessionStatus.failed, Session.started_at >= now - win)
        .group_by(Session.patient_id)
    ).all())

    items = []
    for pid, name, ext, affected, created in patients:
        flags = _patient_flags(p, metric, now, windows, moments.get(pid, {}), affected,
                               last_session.get(pid), created, sensor.get(pid), int(failed.get(pid, 0)))
        if not flags:
            continue
        for f in flags:
            f["severity"] = SEVERITY[f["kind"]]
        flags.sort(key=lambda f: -f["severity"])
        last = last_session.get(pid)
        items.append({
            "patient": {"id": pid, "display_name": name, "external_id": ext, "affected_leg": affected},
            "severity": flags[0]["severity"], "flags": flags,
            "last_session_at": as_utc(last) if last else None,
        })
    epoch = datetime.min.replace(tzinfo=UTC)
    items.sort(key=lambda it: (-it["severity"], -len(it["flags"]), it["last_session_at"] or epoch,
                               it["patient"]["id"]))
    page = items[offset:offset + limit]
    _render(page, now)
    return {
        "items": page, "next_cursor": str(offset + limit) if offset + limit < len(items) else None,
        "n_flagged": len(items), "n_patients": len(patients), "generated_at": now.isoformat(),
        "params": asdict(p),
    }
