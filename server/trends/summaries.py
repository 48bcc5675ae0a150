"""Keep the per session, leg and activity trend summaries in step with the stride table.

``refresh_session`` is called by the job runner after every processing run (success or failure); ``backfill``
creates summaries for processed sessions that lack them (sessions processed before this module existed, or whose
summary is older than their last processing run).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from sqlalchemy import delete, exists, func, or_, select
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.codec import encode_values
from server.enums import SessionStatus, StrideActivity
from server.results.models import Stride
from server.sessions.models import Batch, Session, SessionSensor
from server.trends.attention.evidence import patients_needing_evidence, refresh_patient
from server.trends.metrics import METRICS, MIN_QUALITY, STRIDE_METRICS
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.stats import quantiles_sorted
from server.utc import utcnow

log = logging.getLogger(__name__)

_COLUMNS = sorted({METRICS[m].column for m in STRIDE_METRICS if METRICS[m].column})


def _quantiles(sorted_values: np.ndarray) -> dict[str, float | None]:
    if not sorted_values.size:
        return {"median": None, "p10": None, "p90": None}
    p10, median, p90 = quantiles_sorted(sorted_values, (0.1, 0.5, 0.9))
    return {"median": median, "p10": p10, "p90": p90}


def summarise_leg(columns: dict[str, np.ndarray], quality: np.ndarray, fallback: np.ndarray, *,
                  walking_s: float | None = None, n_gaps: int = 0) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The summary of one leg and activity of one session from its stride columns (arrays in stride order).

    Returns the :class:`TrendSessionLeg` counts and one :class:`TrendMetricValues` field dict per stride metric.
    A stride is included in a metric when quality >= MIN_QUALITY and its value is within the metric's limits.
    """
    ok = np.nan_to_num(np.asarray(quality, dtype=np.float64), nan=0.0) >= MIN_QUALITY
    durations = columns.get("duration_s", np.empty(0))
    leg_row = {
        "n_strides": int(ok.size), "n_low_quality": int((~ok).sum()),
        "n_fallback": int(np.count_nonzero(np.asarray(fallback, dtype=bool))),
        "n_gaps": int(n_gaps),
        "walking_s": float(walking_s) if walking_s is not None else float(np.nansum(durations)),
    }
    metric_rows = []
    implausible = np.zeros(int(ok.sum()), dtype=bool)
    for name in STRIDE_METRICS:
        metric = METRICS[name]
        vals = metric.values(np.asarray(columns[metric.column], dtype=np.float64)[ok])
        keep = metric.plausible(vals)
        if metric.unit == "deg":
            implausible |= ~keep
        inc = np.sort(vals[keep])  # ascending: bucket quantiles of one session need no sort at query time
        metric_rows.append({
            "metric": name, "n_included": int(inc.size), "n_implausible": int((~keep).sum()),
            "mean": float(inc.mean()) if inc.size else None,
            "sd": float(inc.std(ddof=1)) if inc.size >= 2 else None,
            **_quantiles(inc),
            "values": encode_values(inc),
        })
    leg_row["n_implausible"] = int(implausible.sum())
    return leg_row, metric_rows


def sensor_coverage(spans: dict[str, tuple[float, float]], sensor_legs: dict[str, str]) -> dict[str, float]:
    """Per leg: the share of the session's recording span (first to last sample of any sensor) that the leg's
    sensors delivered data for, the shorter of its sensors' spans. A sensor that stops (or starts) mid-session
    shows as coverage well below 1; lost packets inside the span do not lower it (they are judged by the strides
    they cost)."""
    if not spans:
        return {}
    t0 = min(a for a, _ in spans.values())
    t1 = max(b for _, b in spans.values())
    if t1 <= t0:
        return {}
    out: dict[str, float] = {}
    for sensor, (a, b) in spans.items():
        leg = sensor_legs.get(sensor)
        if leg is not None:
            out[leg] = min(out.get(leg, 1.0), max(0.0, (b - a) / (t1 - t0)))
    return out


def expected_strides(n_strides: dict[tuple[str, str], int], coverage: dict[str, float]) -> dict[tuple[str, str], int]:
    """Strides each (leg, activity) should have given: both legs walk the same cycles, so the most any leg gave in
    that activity; a lone leg whose sensors stopped early is scaled up to full coverage (walking assumed evenly
    spread over the session)."""
    out = {}
    for (leg, activity), n in n_strides.items():
        others = [m for (g, a), m in n_strides.items() if a == activity and g != leg]
        if others:
            out[(leg, activity)] = max(n, *others)
        else:
            cov = coverage.get(leg)
            out[(leg, activity)] = int(round(n / cov)) if cov and cov > 0.05 else n
    return out


def refresh_session(db: DbSession, session_id: str) -> int:
    """Replace the trend summaries of one session from its Stride rows; returns the number of rows summarised
    (one per leg and activity).

    Only sessions with status ``done`` get summaries (a failed run leaves none, so its strides never enter a
    trend). Walking and running strides of one leg are summarised apart: a trend never pools them. Flushes; the
    caller commits.
    """
    db.execute(delete(TrendMetricValues).where(TrendMetricValues.session_id == session_id))
    db.execute(delete(TrendSessionLeg).where(TrendSessionLeg.session_id == session_id))
    sess = db.get(Session, session_id)
    if sess is None or sess.status != SessionStatus.done:
        db.flush()
        if sess is not None:
            refresh_patient(db, sess.patient_id)  # a failed run counts for sensor trouble
        return 0
    cols = [getattr(Stride, c) for c in _COLUMNS]
    rows = db.execute(
        select(Stride.leg, Stride.activity, Stride.quality, Stride.fallback, *cols)
        .where(Stride.session_id == session_id).order_by(Stride.leg, Stride.index)
    ).all()
    legs_summary = ((sess.summary or {}).get("legs") or {}) if isinstance(sess.summary, dict) else {}
    sensor_legs = db.execute(
        select(SessionSensor.leg).where(SessionSensor.session_id == session_id).distinct()
    ).scalars().all()
    groups = _leg_activities(rows, [*sensor_legs, *legs_summary], legs_summary, sess.activity)
    coverage = sensor_coverage(*_sensor_spans(db, session_id))
    expected = expected_strides({g: sum(1 for r in rows if (r.leg, r.activity) == g) for g in groups}, coverage)
    now = utcnow()
    for leg, activity in groups:
        group = [r for r in rows if r.leg == leg and r.activity == activity]
        info = legs_summary.get(leg) or {}
        columns = {c: np.array([getattr(r, c) for r in group], dtype=np.float64) for c in _COLUMNS}
        # The leg's time and gaps belong to the activity the leg was processed as.
        own = activity == _leg_activity(info, {a for g, a in groups if g == leg}, sess.activity)
        leg_row, metric_rows = summarise_leg(
            columns, np.array([r.quality for r in group], dtype=np.float64),
            np.array([bool(r.fallback) for r in group], dtype=bool),
            walking_s=info.get("walking_s") if own else None, n_gaps=int(info.get("gaps") or 0) if own else 0)
        key = {"session_id": session_id, "leg": leg, "activity": activity, "patient_id": sess.patient_id,
               "started_at": sess.started_at}
        db.add(TrendSessionLeg(**key, **leg_row, n_expected=expected[(leg, activity)], coverage=coverage.get(leg),
                               algorithm_version=sess.algorithm_version, refreshed_at=now))
        for mr in metric_rows:
            db.add(TrendMetricValues(**key, **mr))
    db.flush()
    refresh_patient(db, sess.patient_id)
    return len(groups)


def _sensor_spans(db: DbSession, session_id: str) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """First and last sample time [ms] of every sensor that sent data, and each sensor's leg."""
    spans = {sid: (float(a), float(b)) for sid, a, b in db.execute(
        select(Batch.sensor_id, func.min(Batch.t_first_ms), func.max(Batch.t_last_ms))
        .where(Batch.session_id == session_id).group_by(Batch.sensor_id))}
    legs = dict(db.execute(select(SessionSensor.sensor_id, SessionSensor.leg)
                           .where(SessionSensor.session_id == session_id)).all())
    return spans, legs


def _leg_activity(info: dict[str, Any], stride_activities: set[str], session_activity: str | None) -> str:
    """The activity a leg was processed as: the pipeline's diagnostics, else the one activity of its strides, else
    what the session's activity implies."""
    diagnostics = info.get("diagnostics")
    said = diagnostics.get("activity") if isinstance(diagnostics, dict) else None
    if said in set(StrideActivity):
        return StrideActivity(said)
    if len(stride_activities) == 1:
        return StrideActivity(next(iter(stride_activities)))
    return StrideActivity.of_session(session_activity)


def _leg_activities(rows: list[Any], other_legs: list[str], legs_summary: dict[str, Any],
                    session_activity: str | None) -> list[tuple[str, str]]:
    """(leg, activity) pairs to summarise: every pair with strides, and every leg without strides once (so its
    gaps and time still count, under the activity it was processed as)."""
    pairs = {(r.leg, r.activity) for r in rows}
    with_strides = {leg for leg, _ in pairs}
    for leg in set(other_legs) - with_strides:
        pairs.add((leg, _leg_activity(legs_summary.get(leg) or {}, set(), session_activity)))
    return sorted(pairs)


def stale_session_ids(db: DbSession, limit: int | None = None) -> list[str]:
    """Processed sessions without a summary, or whose summary predates their last processing run."""
    newest = (select(func.min(TrendSessionLeg.refreshed_at)).where(TrendSessionLeg.session_id == Session.id)
              .scalar_subquery())
    q = (select(Session.id).where(Session.status == SessionStatus.done)
         .where(or_(~exists().where(TrendSessionLeg.session_id == Session.id),
                    Session.processed_at > newest))
         .order_by(Session.started_at))
    if limit is not None:
        q = q.limit(limit)
    return list(db.execute(q).scalars())


def backfill(factory: sessionmaker[DbSession], *, batch: int = 200) -> int:
    """Summarise every processed session lacking an up-to-date summary, committing per batch; returns the count."""
    with factory() as db:
        ids = stale_session_ids(db)
    # One pass over a fixed list: a session that yields no legs must not make this loop forever.
    for start in range(0, len(ids), batch):
        with factory() as db:
            for sid in ids[start:start + batch]:
                refresh_session(db, sid)
            db.commit()
    with factory() as db:
        for pid in patients_needing_evidence(db):
            refresh_patient(db, pid)
        db.commit()
    if ids:
        log.info("trend summaries backfilled for %d sessions", len(ids))
    return len(ids)
