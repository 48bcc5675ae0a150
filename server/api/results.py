"""Results of a processed session: strides and the continuous knee angle (down-sampled)."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Query
from sqlalchemy import select

from server.api.common import Caller, Db, aware, finite_or_none
from server.auth import get_session_for
from server.errors import ProblemError, invalid, not_found
from server.jobs.traces import decode_trace
from server.models import KneeAngleTrace, Session, Stride
from server.schemas import KneeAngleOut, Leg, StrideOut, StridesOut

router = APIRouter(prefix="/v1/sessions", tags=["results"])


def _require_done(session: Session) -> None:
    if session.status == "done":
        return
    detail = f"The session is {session.status}; results exist once it is done"
    if session.status == "failed" and session.error:
        detail += f" (processing failed: {session.error})"
    raise ProblemError(409, detail, title="Results not available", slug="results-not-ready")


@router.get("/{session_id}/strides", response_model=StridesOut,
            summary="Every stride of the session (optionally one leg), heel strike to heel strike")
def get_strides(session_id: str, db: Db, caller: Caller, leg: Leg | None = Query(None)) -> StridesOut:
    session = get_session_for(db, caller, session_id)
    _require_done(session)
    stmt = select(Stride).where(Stride.session_id == session.id)
    if leg is not None:
        stmt = stmt.where(Stride.leg == leg)
    rows = db.scalars(stmt.order_by(Stride.leg, Stride.index)).all()
    strides = [StrideOut(
        leg=r.leg, index=r.index, started_at=aware(r.started_at),  # type: ignore[arg-type]
        t_start_s=r.t_start_s, t_end_s=r.t_end_s, duration_s=finite_or_none(r.duration_s),
        t_toe_off_s=finite_or_none(r.t_toe_off_s), stance_time_s=finite_or_none(r.stance_time_s),
        swing_time_s=finite_or_none(r.swing_time_s), stance_pct=finite_or_none(r.stance_pct),
        peak_swing_flexion_deg=finite_or_none(r.peak_swing_flexion_deg),
        min_flexion_deg=finite_or_none(r.min_flexion_deg), rom_deg=finite_or_none(r.rom_deg),
        stance_flexion_deg=finite_or_none(r.stance_flexion_deg), estimator=r.estimator,
        quality=finite_or_none(r.quality), quality_reasons=list(r.quality_reasons or []),
    ) for r in rows]
    return StridesOut(session_id=session.id, strides=strides)


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


@router.get("/{session_id}/knee-angle", response_model=KneeAngleOut,
            summary="The continuous knee flexion estimate of one leg, min/max down-sampled to max_points")
def get_knee_angle(session_id: str, db: Db, caller: Caller,
                   leg: Leg | None = Query(None, description="Required when both legs were measured"),
                   max_points: int = Query(2000, ge=10, le=200_000),
                   start_s: float | None = Query(None, description="Window start, s since session start"),
                   end_s: float | None = Query(None, description="Window end, s since session start")) -> KneeAngleOut:
    session = get_session_for(db, caller, session_id)
    _require_done(session)
    traces = db.scalars(select(KneeAngleTrace).where(KneeAngleTrace.session_id == session.id)).all()
    if leg is None:
        if len(traces) > 1:
            raise invalid("leg", "this session has both legs; choose leg=left or leg=right")
        if not traces:
            raise not_found("Knee angle trace")
        trace = traces[0]
    else:
        trace = next((tr for tr in traces if tr.leg == leg), None)
        if trace is None:
            raise not_found(f"Knee angle of the {leg} leg")
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise invalid("end_s", "end_s must be after start_s")
    t, angle, est = decode_trace(trace.t0_s, trace.fs_hz, trace.n, trace.angle_deg, trace.estimator_codes,
                                 trace.estimator_names)
    keep = np.ones(len(t), dtype=bool)
    if start_s is not None:
        keep &= t >= start_s
    if end_s is not None:
        keep &= t <= end_s
    t, angle, est = t[keep], angle[keep], est[keep]
    idx = minmax_indices(angle, max_points)
    finite = np.isfinite(angle[idx])
    angles = np.round(angle[idx], 3)
    return KneeAngleOut(
        session_id=session.id, leg=trace.leg, fs_hz=trace.fs_hz,  # type: ignore[arg-type]
        n_total=len(t), downsampling="minmax" if len(idx) < len(t) else "none",
        t_s=np.round(t[idx], 4).tolist(),
        angle_deg=[float(a) if f else None for a, f in zip(angles.tolist(), finite.tolist(), strict=True)],
        estimator=[str(e) if (e and f) else None for e, f in zip(est[idx].tolist(), finite.tolist(), strict=True)],
    )
