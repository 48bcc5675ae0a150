"""Results of a processed session: strides and the continuous knee angle (down-sampled)."""

from __future__ import annotations

from functools import partial
from typing import Any

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool

from server.auth.service import get_session_for
from server.deps import Caller, Db
from server.enums import Leg, SessionStatus
from server.errors import ProblemError, invalid, not_found
from server.numbers import finite_round
from server.results import compare, service
from server.results.schemas import CompareOut, KneeAngleOut, StrideOut, StridesOut
from server.results.stride_record import STORED_FLOATS
from server.sessions.models import Session

router = APIRouter(prefix="/v1/sessions", tags=["results"])


def _require_done(session: Session) -> None:
    if session.status == SessionStatus.done:
        return
    detail = f"The session is {session.status}; results exist once it is done"
    if session.status == SessionStatus.failed and session.error:
        detail += f" (processing failed: {session.error})"
    raise ProblemError(409, detail, title="Results not available", slug="results-not-ready")


@router.get("/{session_id}/strides", response_model=StridesOut, operation_id="listStrides",
            responses={409: {"description": "The session is not processed (yet, or processing failed)"}},
            summary="Every stride of the session (optionally one leg), heel strike to heel strike")
def get_strides(session_id: str, db: Db, caller: Caller, leg: Leg | None = Query(None)) -> StridesOut:
    """Every stride of a processed session (optionally one leg)."""
    session = get_session_for(db, caller, session_id)
    _require_done(session)
    rows = service.strides(db, session.id, leg)
    return StridesOut(session_id=session.id, strides=[stride_out(r) for r in rows])


def stride_out(r: Any) -> StrideOut:
    """The response form of a stored stride row (:func:`server.results.service.strides`): the value fields of
    :mod:`server.results.stride_record`."""
    values = {name: finite_round(getattr(r, name), None) for name in STORED_FLOATS}
    return StrideOut(leg=r.leg, index=r.index, started_at=r.started_at, estimator=r.estimator,
                     activity=r.activity, fallback=r.fallback, quality_reasons=list(r.quality_reasons or []),
                     **values)


@router.get("/{session_id}/knee-angle", response_model=KneeAngleOut,
            responses={409: {"description": "The session is not processed (yet, or processing failed)"}},
            summary="The continuous knee flexion estimate of one leg, min/max down-sampled to max_points")
def get_knee_angle(session_id: str, db: Db, caller: Caller,
                   leg: Leg | None = Query(None, description="Required when both legs were measured"),
                   max_points: int = Query(2000, ge=10, le=200_000),
                   start_s: float | None = Query(None, description="Window start, s since session start"),
                   end_s: float | None = Query(None, description="Window end, s since session start")) -> KneeAngleOut:
    """The continuous knee angle of one leg, min/max down-sampled to at most ``max_points``."""
    session = get_session_for(db, caller, session_id)
    _require_done(session)
    traces = service.traces(db, session.id)
    if leg is None:
        if len(traces) > 1:
            raise invalid("leg", "this session has both legs; choose leg=left or leg=right")
        if not traces:
            raise not_found("Knee angle trace")
        trace = next(iter(traces.values()))
    else:
        trace = traces.get(leg)
        if trace is None:
            raise not_found(f"Knee angle of the {leg} leg")
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise invalid("end_s", "end_s must be after start_s")
    w = service.trace_window(trace, start_s=start_s, end_s=end_s, max_points=max_points)
    finite = np.isfinite(w.angle_deg)
    angles = np.round(w.angle_deg, 3)
    return KneeAngleOut(
        session_id=session.id, leg=Leg(w.leg), fs_hz=w.fs_hz,
        n_total=w.n_total, downsampling="minmax" if w.downsampled else "none",
        t_s=np.round(w.t_s, 4).tolist(),
        angle_deg=[float(a) if f else None for a, f in zip(angles.tolist(), finite.tolist(), strict=True)],
        estimator=[str(e) if (e and f) else None for e, f in zip(w.estimator.tolist(), finite.tolist(), strict=True)],
        withheld=_withheld(session.summary, w.leg),
        not_worn_s=_not_worn(session.summary, w.leg),
    )


def _diagnostic(summary: dict | None, leg: str, key: str) -> object:
    """One entry of the leg's diagnostics (pipeline.types.LegDiagnostics) in the session's stored summary."""
    legs = summary.get("legs") if isinstance(summary, dict) else None
    entry = legs.get(leg) if isinstance(legs, dict) else None
    diag = entry.get("diagnostics") if isinstance(entry, dict) else None
    return diag.get(key) if isinstance(diag, dict) else None


def _withheld(summary: dict | None, leg: str) -> str | None:
    """The leg's ``trace_withheld`` diagnostic, None for sessions stored before it."""
    value = _diagnostic(summary, leg, "trace_withheld")
    return value if isinstance(value, str) else None


def _not_worn(summary: dict | None, leg: str) -> list[tuple[float, float]]:
    """The leg's ``not_worn_s`` diagnostic, empty for sessions stored before it."""
    value = _diagnostic(summary, leg, "not_worn_s")
    if not isinstance(value, list):
        return []
    return [(float(a), float(b)) for a, b in value if isinstance(a, int | float) and isinstance(b, int | float)]


@router.get("/{session_id}/compare", response_model=CompareOut,
            responses={409: {"description": "The session is still receiving or has no uploaded data"}},
            summary="Every knee estimator on this session: stride metrics per estimator and pairwise differences")
async def compare_session(session_id: str, request: Request, caller: Caller,
                          estimators: str | None = Query(None, description="Comma-separated subset, e.g. go,kf; "
                                                                           "default: auto and every registered one")
                          ) -> CompareOut:
    """Every knee estimator on this session (see :mod:`server.results.compare`)."""
    names = compare.requested_estimators(estimators)
    factory = request.app.state.sessionmaker
    # Threads: the database read and the pipeline runs block; the event loop keeps serving meanwhile.
    inp = await run_in_threadpool(compare.load_input, factory, caller, session_id, names)
    try:
        return await run_in_threadpool(compare.run_compare, inp)
    except LookupError:
        inp = await run_in_threadpool(partial(compare.load_input, with_streams=True), factory, caller, session_id,
                                      names)
        return await run_in_threadpool(compare.run_compare, inp)
