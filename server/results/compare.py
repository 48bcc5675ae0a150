"""Every knee estimator side by side on one session: where do they agree, where not?

``GET /v1/sessions/{session_id}/compare`` re-runs the pipeline on the stored raw data once per estimator (``auto``,
the policy the stored results come from, and each registered estimator: ``go`` Allseits et al. 2018, ``cf`` Seel /
Rhudy Eq. 17, ``kf`` Rhudy Eq. 18-21, ``ekf`` Rhudy Eq. 22-24) and returns per leg the per-stride metric summary of
each and the RMS difference between every pair of continuous angle estimates. Nothing is stored in the database.

The raw data are read in one short transaction that is closed before the pipeline runs (seconds for a long
session, in a worker thread), so a comparison never holds a database connection while it computes. The last few
answers are kept in memory, keyed by the session's uploaded content, the algorithm version, the normalised
estimator set (``go,kf`` and ``kf,go,go`` are one comparison) and the knee calibrations valid at the session's
start (the ones its processing uses, :mod:`server.calibrations.service`).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from pipeline import ALGORITHM_VERSION
from pipeline.estimators import available
from pipeline.session import process_session
from pipeline.types import KneeCalibration, RawSensorStream, SessionResult
from server.auth.service import Principal, get_session_for
from server.calibrations import service as calibrations
from server.config import get_settings
from server.enums import SessionStatus
from server.errors import ProblemError, invalid
from server.numbers import finite_round
from server.results.schemas import CompareOut, EstimatorSummary, LegComparison, MetricSummary, PairDifference
from server.sessions.bounds import session_span_problem
from server.sessions.models import Batch
from server.sessions.rawdata import CHUNKING, load_streams

log = logging.getLogger("gaitmon.compare")

METRICS = ("peak_swing_flexion_deg", "rom_deg", "min_flexion_deg")
CACHE_SIZE = 8
AUTO = "auto"


def known_estimators() -> list[str]:
    """What a comparison can run, in its canonical order: the auto policy first, then the registry's order."""
    return [AUTO, *available()]


def requested_estimators(raw: str | None) -> tuple[str, ...]:
    """The estimators of a ``?estimators=`` value in the order asked for, de-duplicated; every known one for None.

    Raises a 422 problem naming the unknown names (or the empty list).
    """
    known = known_estimators()
    if raw is None:
        return tuple(known)
    names = tuple(dict.fromkeys(e.strip() for e in raw.split(",") if e.strip()))
    unknown = [e for e in names if e not in known]
    if unknown or not names:
        raise invalid("estimators", f"unknown estimator(s) {', '.join(unknown) or '(none given)'}; "
                                    f"available: {', '.join(known)}")
    return names


def estimator_set(names: tuple[str, ...]) -> tuple[str, ...]:
    """The cache key part of an estimator list: sorted and de-duplicated (the order asked for changes nothing)."""
    return tuple(sorted(set(names)))


@dataclass(frozen=True)
class CompareInput:
    """Everything a comparison needs, read from the database; the key says what it depends on."""

    session_id: str
    activity: str
    estimators: tuple[str, ...]
    key: Hashable
    streams: list[RawSensorStream] | None  # None when the answer is cached
    calibration: dict[str, KneeCalibration]  # per leg, the one the session's processing would use


_cache: OrderedDict[tuple, CompareOut] = OrderedDict()  # (session, content, version, estimators) -> answer
_cache_lock = threading.Lock()


def _summary(values: list[float]) -> MetricSummary:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if v.size == 0:
        return MetricSummary(mean=None, median=None, sd=None)
    return MetricSummary(mean=finite_round(float(v.mean()), 2), median=finite_round(float(np.median(v)), 2),
                         sd=finite_round(float(v.std(ddof=1)), 2) if v.size > 1 else None)


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
                rms_deg=finite_round(float(np.sqrt(np.mean(d ** 2))), 2) if d.size else None,
                mean_deg=finite_round(float(d.mean()), 2) if d.size else None))
        out[leg] = LegComparison(estimators=summaries, pairs=pairs)
    return out


def _refuse_long(first_ms: float, last_ms: float) -> None:
    """Compare runs every estimator on the whole session inside the API process, so it is limited to sessions of
    at most one processing chunk (longer ones are processed chunk by chunk by the workers only)."""
    span_s = (float(last_ms) - float(first_ms)) / 1000.0
    if span_s > CHUNKING.chunk_s:
        raise ProblemError(422, f"The session spans {span_s / 60:.0f} min; estimators are compared on sessions of "
                           f"at most {CHUNKING.chunk_s / 60:.0f} min", title="Session too long to compare",
                           slug="session-too-long-to-compare")


def load_input(factory: sessionmaker[DbSession], principal: Principal, session_id: str,
               estimators: tuple[str, ...], *, with_streams: bool = False) -> CompareInput:
    """Check access and readiness and read the raw data (unless the answer is cached and ``with_streams`` is
    False) in one short transaction."""
    with factory() as db:
        session = get_session_for(db, principal, session_id)
        if session.status == SessionStatus.receiving:
            raise ProblemError(409, "The session is still receiving data; compare it once it is complete",
                               title="Comparison not available", slug="compare-not-ready")
        n_batches, last_batch, first_ms, last_ms = db.execute(
            select(func.count(), func.max(Batch.id), func.min(Batch.t_first_ms), func.max(Batch.t_last_ms))
            .where(Batch.session_id == session.id)).one()
        if not n_batches:
            raise ProblemError(409, "The session has no uploaded data", title="Comparison not available",
                               slug="compare-not-ready")
        problem = session_span_problem(db, session.id, get_settings().max_session_s)
        if problem is not None:
            raise ProblemError(422, f"The session cannot be compared: {problem}", title="Session out of bounds",
                               slug="session-out-of-bounds")
        _refuse_long(first_ms, last_ms)
        calibration = calibrations.for_pipeline(calibrations.applicable(db, session.patient_id, session.started_at))
        levels = tuple(sorted((leg, c.calibration_id, c.standing_knee_deg) for leg, c in calibration.items()))
        key = (session.id, n_batches, last_batch, session.activity, ALGORITHM_VERSION, estimator_set(estimators),
               levels)
        with _cache_lock:
            cached = key in _cache
        streams = None if cached and not with_streams else load_streams(db, session.id)
        return CompareInput(session.id, session.activity, estimators, key, streams, calibration)


def run_compare(inp: CompareInput) -> CompareOut:
    """The comparison (from the cache, or by running the pipeline once per estimator; CPU-bound, no database)."""
    with _cache_lock:
        if inp.key in _cache:
            _cache.move_to_end(inp.key)
            cached = _cache[inp.key]
            order = [e for e in inp.estimators if e in cached.estimators]
            return cached if order == cached.estimators else cached.model_copy(update={"estimators": order})
    if inp.streams is None:  # evicted since it was looked up: the caller reads the data after all
        raise LookupError(inp.key)
    results: dict[str, SessionResult] = {}
    failed: dict[str, str] = {}
    for name in inp.estimators:
        try:
            results[name] = process_session(inp.streams, activity=inp.activity, estimator=name,
                                            calibration=inp.calibration)
        except Exception as exc:  # noqa: BLE001 - one estimator failing must not hide the others
            log.warning("compare %s: estimator %s failed: %s", inp.session_id, name, exc)
            failed[name] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    warnings = next((list(r.warnings) for r in results.values()), [])
    log.info("compare %s: %s", inp.session_id, ", ".join(results))
    out = CompareOut(session_id=inp.session_id, activity=inp.activity, algorithm_version=ALGORITHM_VERSION,
                     estimators=list(results), failed=failed, legs=compare_results(results), warnings=warnings)
    with _cache_lock:
        _cache[inp.key] = out
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return out
