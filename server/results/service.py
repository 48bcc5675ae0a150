"""Reading a processed session's results: its strides, its knee-angle traces (windowed, min/max down-sampled) and
the knee angle over the gait cycle. The API routes and the clinician pages both read through here."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

from server.codec import decode_trace
from server.results.models import KneeAngleTrace, Stride
from server.trends.metrics import stride_exclusions

CYCLE_POINTS = 101  # 0, 1, ..., 100 % of the gait cycle


def strides(db: DbSession, session_id: str, leg: str | None = None) -> list[Any]:
    """Every stored stride of the session (optionally one leg) by leg and index, as rows with the Stride columns
    as attributes (core rows: a long session has thousands of strides and ORM objects cost ~10x more)."""
    stmt = select(*Stride.__table__.c).where(Stride.session_id == session_id)
    if leg is not None:
        stmt = stmt.where(Stride.leg == leg)
    return list(db.execute(stmt.order_by(Stride.leg, Stride.index)).all())


def traces(db: DbSession, session_id: str) -> dict[str, KneeAngleTrace]:
    """The session's stored knee-angle trace of each leg, by leg."""
    rows = db.scalars(select(KneeAngleTrace).where(KneeAngleTrace.session_id == session_id)).all()
    return {r.leg: r for r in rows}


def minmax_indices(angle_deg: np.ndarray, max_points: int) -> np.ndarray:
    """Indices of a min/max-preserving down-sample to at most ``max_points`` samples.

    The trace is cut into ``max_points // 2`` equal buckets; each keeps its smallest and largest finite sample in
    time order, so peak swing flexion and full extension survive any zoom level (plain striding would drop them).
    A bucket with no finite sample keeps its first sample (null), so a gap longer than a bucket still breaks
    the plotted line; a gap shorter than a bucket is bridged.
    """
    n = len(angle_deg)
    if n <= max_points:
        return np.arange(n)
    n_buckets = max(1, max_points // 2)
    k = -(-n // n_buckets)
    rows = -(-n // k)
    padded = np.full(rows * k, np.nan)
    padded[:n] = angle_deg
    grid = padded.reshape(rows, k)
    empty = np.all(np.isnan(grid), axis=1)
    lo = np.argmin(np.where(np.isnan(grid), np.inf, grid), axis=1)
    hi = np.argmax(np.where(np.isnan(grid), -np.inf, grid), axis=1)
    lo[empty] = 0
    hi[empty] = 0
    base = np.arange(rows) * k
    return np.unique(np.concatenate([base + lo, base + hi]))


@dataclass(frozen=True)
class TraceWindow:
    """A leg's knee angle inside a time window, min/max down-sampled; shapes (n,) each.

    ``n_total`` is how many stored samples lie in the window; ``t_first_s``/``t_last_s`` span the whole trace."""

    leg: str
    fs_hz: float
    t_s: np.ndarray
    angle_deg: np.ndarray
    estimator: np.ndarray
    n_total: int
    t_first_s: float
    t_last_s: float

    @property
    def downsampled(self) -> bool:
        """True when the window held more samples than were kept."""
        return len(self.t_s) < self.n_total


def trace_window(trace: KneeAngleTrace, *, start_s: float | None, end_s: float | None,
                 max_points: int) -> TraceWindow:
    """The stored trace in [start_s, end_s] (either bound may be open), down-sampled by :func:`minmax_indices`."""
    t, angle, est = decode_trace(trace.t0_s, trace.fs_hz, trace.n, trace.angle_deg, trace.estimator_codes,
                                 trace.estimator_names)
    t_first = float(t[0]) if len(t) else 0.0
    t_last = float(t[-1]) if len(t) else 0.0
    keep = np.ones(len(t), dtype=bool)
    if start_s is not None:
        keep &= t >= start_s
    if end_s is not None:
        keep &= t <= end_s
    t, angle, est = t[keep], angle[keep], est[keep]
    idx = minmax_indices(angle, max_points)
    return TraceWindow(trace.leg, float(trace.fs_hz), t[idx], angle[idx], est[idx], int(len(t)), t_first, t_last)


@dataclass(frozen=True)
class Cycle:
    """Knee angle over the gait cycle (0-100 %, heel strike to heel strike) of the included strides of one leg."""

    leg: str
    n_strides: int
    mean_deg: list[float | None]
    sd_deg: list[float | None]
    toe_off_pct: float | None  # mean stance phase of these strides: where swing starts


def gait_cycles(db: DbSession, session_id: str, rows: list[Any] | None = None,
                excluded: list[list[str]] | None = None,
                stored: dict[str, KneeAngleTrace] | None = None) -> dict[str, Cycle]:
    """Per leg: each included stride's stored angle trace resampled to 0..100 % between its heel strikes, then
    mean and SD across strides at every percent.

    ``rows`` are the session's :func:`strides`, ``excluded`` per stride why it does not count in the trends (empty:
    it counts; :func:`server.trends.summaries.stride_exclusions`), ``stored`` its :func:`traces`; each is read here
    when the caller has not. Excluded strides and strides that cross a gap in the trace are left out. A session
    without a stored trace has no cycle, and its strides are not read at all (a patient's first session may be one)."""
    if stored is None:
        stored = traces(db, session_id)
    if not stored:
        return {}
    if rows is None:
        rows = strides(db, session_id)
    if excluded is None:
        excluded = stride_exclusions(rows)
    by_leg: dict[str, list[Any]] = {}
    for s, why in zip(rows, excluded, strict=True):
        if not why:
            by_leg.setdefault(s.leg, []).append(s)
    out: dict[str, Cycle] = {}
    for leg, leg_rows in sorted(by_leg.items()):
        tr = stored.get(leg)
        if tr is not None:
            cycle = _leg_cycle(tr, leg_rows)
            if cycle is not None:
                out[leg] = cycle
    return out


def _leg_cycle(tr: KneeAngleTrace, leg_rows: list[Any]) -> Cycle | None:
    t, angle, _ = decode_trace(tr.t0_s, tr.fs_hz, tr.n, tr.angle_deg, tr.estimator_codes, tr.estimator_names)
    pct = np.linspace(0.0, 1.0, CYCLE_POINTS)
    curves, stance = [], []
    for s in leg_rows:
        i0 = int(np.searchsorted(t, s.t_start_s - 0.5 / tr.fs_hz))
        i1 = int(np.searchsorted(t, s.t_end_s + 0.5 / tr.fs_hz))
        seg_t, seg_a = t[i0:i1], angle[i0:i1]
        if seg_t.size < 10 or not np.all(np.isfinite(seg_a)):
            continue
        curves.append(np.interp(s.t_start_s + pct * (s.t_end_s - s.t_start_s), seg_t, seg_a))
        stance.append(s.stance_pct)
    if not curves:
        return None
    arr = np.vstack(curves)
    mean = arr.mean(axis=0)
    sd = arr.std(axis=0, ddof=1) if len(curves) > 1 else np.full(CYCLE_POINTS, np.nan)
    toe_off = float(np.nanmean(np.asarray(stance, dtype=np.float64))) if stance else None
    return Cycle(tr.leg, len(curves), [_num(v) for v in mean], [_num(v) for v in sd],
                 toe_off if toe_off is not None and math.isfinite(toe_off) else None)


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None
