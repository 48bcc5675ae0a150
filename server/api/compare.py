"""Every knee estimator side by side on one session: where do they agree, where not?

``GET /v1/sessions/{session_id}/compare`` re-runs the pipeline on the stored raw data once per estimator (``auto``,
the policy the stored results come from, and each registered estimator: ``go`` Allseits et al. 2018, ``cf`` Seel /
Rhudy Eq. 17, ``kf`` Rhudy Eq. 18-21, ``ekf`` Rhudy Eq. 22-24) and returns per leg the per-stride metric summary of
each and the RMS difference between every pair of continuous angle estimates. Nothing is stored in the database;
the call costs a few pipeline runs (seconds for a long session), so the last few answers are kept in memory, keyed
by the session's uploaded content and the algorithm version.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from itertools import combinations

import numpy as np
from fastapi import APIRouter, Query
from pydantic import BaseModel, Field
from sqlalchemy import func, select

from pipeline import ALGORITHM_VERSION
from pipeline.estimators import available
from pipeline.session import process_session
from pipeline.types import SessionResult
from server.api.common import Caller, Db
from server.auth import get_session_for
from server.errors import ProblemError, invalid
from server.models import Batch
from server.rawdata import load_streams

log = logging.getLogger("gaitmon.compare")
router = APIRouter(prefix="/v1/sessions", tags=["results"])

METRICS = ("peak_swing_flexion_deg", "rom_deg", "min_flexion_deg")
CACHE_SIZE = 8


class MetricSummary(BaseModel):
    mean: float | None
    median: float | None
    sd: float | None


class EstimatorSummary(BaseModel):
    n_strides: int
    peak_swing_flexion_deg: MetricSummary
    rom_deg: MetricSummary
    min_flexion_deg: MetricSummary
    stride_estimators: dict[str, int] = Field(description="Strides per estimator that produced them (auto mixes)")


class PairDifference(BaseModel):
    a: str
    b: str
    rms_deg: float | None = Field(description="RMS of the sample-wise difference of the two angle traces")
    mean_deg: float | None = Field(description="Mean of a - b: the part of the difference that is an offset")
    n_samples: int


class LegComparison(BaseModel):
    estimators: dict[str, EstimatorSummary]
    pairs: list[PairDifference]


class CompareOut(BaseModel):
    session_id: str
    activity: str
    algorithm_version: str
    estimators: list[str]
    failed: dict[str, str] = Field(description="Estimators that could not run on this session, with the reason")
    legs: dict[str, LegComparison]
    warnings: list[str]


_cache: OrderedDict[tuple, CompareOut] = OrderedDict()  # (session, content, version, estimators) -> answer
_cache_lock = threading.Lock()


def _summary(values: list[float]) -> MetricSummary:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if v.size == 0:
        return MetricSummary(mean=None, median=None, sd=None)
    return MetricSummary(mean=round(float(v.mean()), 2), median=round(float(np.median(v)), 2),
                         sd=round(float(v.std(ddof=1)), 2) if v.size > 1 else None)


def compare_results(results: dict[str, SessionResult]) -> dict[str, LegComparison]:
    """Per leg: the stride-metric summary of every estimator's result and the RMS difference of every pair of angle
    traces (on the samples where both have an estimate; all results share each leg's time grid)."""
    legs = sorted({leg for r in results.values() for leg in r.legs})
    out: dict[str, LegComparison] = {}
    for leg in legs:
        summaries: dict[str, EstimatorSummary] = {}
        traces: dict[str, np.ndarray] = {}
        for name, res in results.items():
            lr = res.legs.get(leg)
            if lr is None:
                continue
            traces[name] = np.asarray(lr.angle_deg, dtype=float)
            counts: dict[str, int] = {}
            for s in lr.strides:
                counts[s.estimator] = counts.get(s.estimator, 0) + 1
            summaries[name] = EstimatorSummary(
                n_strides=len(lr.strides), stride_estimators=counts,
                **{m: _summary([getattr(s, m) for s in lr.strides]) for m in METRICS})
        pairs = []
        for a, b in combinations(list(traces), 2):
            ta, tb = traces[a], traces[b]
            n = min(ta.size, tb.size)
            d = ta[:n] - tb[:n]
            d = d[np.isfinite(d)]
            pairs.append(PairDifference(
                a=a, b=b, n_samples=int(d.size),
                rms_deg=round(float(np.sqrt(np.mean(d ** 2))), 2) if d.size else None,
                mean_deg=round(float(d.mean()), 2) if d.size else None))
        out[leg] = LegComparison(estimators=summaries, pairs=pairs)
    return out


@router.get("/{session_id}/compare", response_model=CompareOut,
            summary="Every knee estimator on this session: stride metrics per estimator and pairwise differences")
def compare_session(session_id: str, db: Db, caller: Caller,
                    estimators: str | None = Query(None, description="Comma-separated subset, e.g. go,kf; "
                                                                     "default: auto and every registered one")
                    ) -> CompareOut:
    session = get_session_for(db, caller, session_id)
    known = ["auto", *available()]
    names = known if estimators is None else [e.strip() for e in estimators.split(",") if e.strip()]
    unknown = [e for e in names if e not in known]
    if unknown or not names:
        raise invalid("estimators", f"unknown estimator(s) {', '.join(unknown) or '(none given)'}; "
                                    f"available: {', '.join(known)}")
    if session.status == "receiving":
        raise ProblemError(409, "The session is still receiving data; compare it once it is complete",
                           title="Comparison not available", slug="compare-not-ready")
    n_batches, last_batch = db.execute(select(func.count(), func.max(Batch.id))
                                       .where(Batch.session_id == session.id)).one()
    if not n_batches:
        raise ProblemError(409, "The session has no uploaded data", title="Comparison not available",
                           slug="compare-not-ready")
    key = (session.id, n_batches, last_batch, session.activity, ALGORITHM_VERSION, tuple(names))
    with _cache_lock:
        if key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
    streams = load_streams(db, session.id)
    results: dict[str, SessionResult] = {}
    failed: dict[str, str] = {}
    for name in dict.fromkeys(names):
        try:
            results[name] = process_session(streams, activity=session.activity, estimator=name)
        except Exception as exc:  # noqa: BLE001 - one estimator failing must not hide the others
            log.warning("compare %s: estimator %s failed: %s", session.id, name, exc)
            failed[name] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    warnings = next((list(r.warnings) for r in results.values()), [])
    log.info("compare %s: %s", session.id, ", ".join(results))
    out = CompareOut(session_id=session.id, activity=session.activity, algorithm_version=ALGORITHM_VERSION,
                     estimators=list(results), failed=failed, legs=compare_results(results), warnings=warnings)
    with _cache_lock:
        _cache[key] = out
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return out
