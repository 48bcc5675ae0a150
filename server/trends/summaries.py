"""Keep the per-session-leg trend summaries in step with the stride table.

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

from server.models import Session, SessionSensor, Stride, utcnow
from server.trends.metrics import METRICS, MIN_QUALITY, PRIMARY_ESTIMATORS, STRIDE_METRICS
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.stats import quantiles_sorted

log = logging.getLogger(__name__)

_COLUMNS = sorted({METRICS[m].column for m in STRIDE_METRICS if METRICS[m].column})


def encode_values(values: np.ndarray) -> bytes:
    return np.ascontiguousarray(values, dtype="<f4").tobytes()


def decode_values(blob: bytes) -> np.ndarray:
    return np.frombuffer(blob, dtype="<f4")


def _quantiles(sorted_values: np.ndarray) -> dict[str, float | None]:
    if not sorted_values.size:
        return {"median": None, "p10": None, "p90": None}
    p10, median, p90 = quantiles_sorted(sorted_values, (0.1, 0.5, 0.9))
    return {"median": median, "p10": p10, "p90": p90}


def summarise_leg(columns: dict[str, np.ndarray], quality: np.ndarray, estimators: list[str], *,
                  walking_s: float | None = None, n_gaps: int = 0) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The summary of one leg of one session from its stride columns (arrays in stride order).

    Returns the :class:`TrendSessionLeg` counts and one :class:`TrendMetricValues` field dict per stride metric.
    A stride is included in a metric when quality >= MIN_QUALITY and its value is within the metric's limits.
    """
    ok = np.nan_to_num(np.asarray(quality, dtype=np.float64), nan=0.0) >= MIN_QUALITY
    durations = columns.get("duration_s", np.empty(0))
    leg_row = {
        "n_strides": int(ok.size), "n_low_quality": int((~ok).sum()),
        "n_fallback": sum(1 for e in estimators if e not in PRIMARY_ESTIMATORS),
        "n_gaps": int(n_gaps),
        "walking_s": float(walking_s) if walking_s is not None else float(np.nansum(durations)),
    }
    metric_rows = []
    for name in STRIDE_METRICS:
        metric = METRICS[name]
        vals = metric.values(np.asarray(columns[metric.column], dtype=np.float64)[ok])
        keep = metric.plausible(vals)
        inc = np.sort(vals[keep])  # ascending: bucket quantiles of one session need no sort at query time
        metric_rows.append({
            "metric": name, "n_included": int(inc.size), "n_implausible": int((~keep).sum()),
            "mean": float(inc.mean()) if inc.size else None,
            "sd": float(inc.std(ddof=1)) if inc.size >= 2 else None,
            **_quantiles(inc),
            "values": encode_values(inc),
        })
    return leg_row, metric_rows


def refresh_session(db: DbSession, session_id: str) -> int:
    """Replace the trend summaries of one session from its Stride rows; returns the number of legs summarised.

    Only sessions with status ``done`` get summaries (a failed run leaves none, so its strides never enter a
    trend). Flushes; the caller commits.
    """
    db.execute(delete(TrendMetricValues).where(TrendMetricValues.session_id == session_id))
    db.execute(delete(TrendSessionLeg).where(TrendSessionLeg.session_id == session_id))
    sess = db.get(Session, session_id)
    if sess is None or sess.status != "done":
        db.flush()
        return 0
    cols = [getattr(Stride, c) for c in _COLUMNS]
    rows = db.execute(
        select(Stride.leg, Stride.quality, Stride.estimator, *cols).where(Stride.session_id == session_id)
        .order_by(Stride.leg, Stride.index)
    ).all()
    legs_summary = ((sess.summary or {}).get("legs") or {}) if isinstance(sess.summary, dict) else {}
    sensor_legs = db.execute(
        select(SessionSensor.leg).where(SessionSensor.session_id == session_id).distinct()
    ).scalars().all()
    legs = sorted({r.leg for r in rows} | set(sensor_legs) | set(legs_summary))
    now = utcnow()
    for leg in legs:
        leg_rows = [r for r in rows if r.leg == leg]
        info = legs_summary.get(leg) or {}
        columns = {c: np.array([getattr(r, c) for r in leg_rows], dtype=np.float64) for c in _COLUMNS}
        leg_row, metric_rows = summarise_leg(
            columns, np.array([r.quality for r in leg_rows], dtype=np.float64), [r.estimator for r in leg_rows],
            walking_s=info.get("walking_s"), n_gaps=int(info.get("gaps") or 0))
        key = {"session_id": session_id, "leg": leg, "patient_id": sess.patient_id, "started_at": sess.started_at}
        db.add(TrendSessionLeg(**key, **leg_row, algorithm_version=sess.algorithm_version, refreshed_at=now))
        for mr in metric_rows:
            db.add(TrendMetricValues(**key, **mr))
    db.flush()
    return len(legs)


def stale_session_ids(db: DbSession, limit: int | None = None) -> list[str]:
    """Processed sessions without a summary, or whose summary predates their last processing run."""
    newest = (select(func.min(TrendSessionLeg.refreshed_at)).where(TrendSessionLeg.session_id == Session.id)
              .scalar_subquery())
    q = (select(Session.id).where(Session.status == "done")
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
    if ids:
        log.info("trend summaries backfilled for %d sessions", len(ids))
    return len(ids)
