"""Claiming and processing queued sessions; shared by the embedded runner, the procrastinate worker and tests.

Exactly-once processing rests on the database, not on the queue: a runner may only work on a session after the
atomic claim ``UPDATE sessions SET status='processing', worker_id=<claim> WHERE id=? AND status='queued'``
changed one row. A job delivered twice, two workers on two machines, or a runner racing the embedded thread: the
second claim changes nothing and that runner skips the session. Results are written only if the claim still
holds (``WHERE worker_id=<claim> AND status='processing'``) in the same transaction that replaces the strides,
so a worker that was presumed dead and came back cannot overwrite the work of the runner that took over.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from datetime import datetime, timedelta

from sqlalchemy import delete, or_, select, update
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server import metadata as _metadata  # noqa: F401 - runners flush rows whose foreign keys span domains
from server.calibrations import service as calibrations
from server.codec import encode_trace
from server.enums import SessionStatus, StrideActivity
from server.numbers import json_safe
from server.ops import metrics as ops_metrics
from server.results.models import KneeAngleTrace, Stride
from server.results.stride_record import STORED_FLOATS
from server.sessions.models import Session
from server.trends.summaries import refresh_session
from server.utc import as_utc, utcnow

log = logging.getLogger("gaitmon.jobs")

# Two kinds of ending without a result, counted apart:
# - an error raised while processing (the pipeline refusing the data, a bug) is final at once: the same data and
#   code raise it again, so the session is "failed" with that error;
# - an interruption (the worker killed or frozen mid-session and its claim recovered, or the database away while
#   processing) says nothing about the data: the session is queued again, up to this many interruptions, so a
#   deploy or two kill -9 never fail an intact recording while a recording that kills every worker (out of
#   memory) still cannot crash-loop them forever.
# Only a claim moves "queued" to "processing" and only reprocess resets ``attempts``, so at a recovery the claims
# so far (``attempts``) are the interruptions so far: every earlier claim ended in one (an error is final).
MAX_INTERRUPTIONS = 10
DEFAULT_HEARTBEAT_S = 10.0
# The database went away (connection lost, pool exhausted): says nothing about the session's data.
DB_UNAVAILABLE = (OperationalError, InterfaceError, PoolTimeoutError)
MAX_ERROR_CHARS = 500


def _update(db: DbSession, session_id: str, *conditions, **values) -> int:  # noqa: ANN002, ANN003
    stmt = (update(Session).where(Session.id == session_id, *conditions).values(**values)
            .execution_options(synchronize_session=False))
    return db.execute(stmt).rowcount


def claim(sm: sessionmaker[DbSession], session_id: str, worker_id: str = "inline") -> str | None:
    """Atomically move a queued session to processing; returns the claim token, or None if someone else has it."""
    token = f"{worker_id[:50]}:{uuid.uuid4().hex[:12]}"
    with sm() as db:
        now = utcnow()
        changed = _update(db, session_id, Session.status == SessionStatus.queued,
                          status=SessionStatus.processing, worker_id=token, heartbeat_at=now,
                          attempts=Session.attempts + 1)
        db.commit()
    return token if changed == 1 else None


def heartbeat(sm: sessionmaker[DbSession], session_id: str, token: str) -> bool:
    """Refresh the claim's heartbeat; False when the claim was lost (recovered by someone else)."""
    with sm() as db:
        changed = _update(db, session_id, Session.worker_id == token, Session.status == SessionStatus.processing,
                          heartbeat_at=utcnow())
        db.commit()
    return changed == 1


class _Heartbeat:
    """Background thread refreshing ``heartbeat_at`` while a session is processed."""

    def __init__(self, sm: sessionmaker[DbSession], session_id: str, token: str, interval_s: float) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(sm, session_id, token, interval_s),
                                        name=f"heartbeat-{session_id[:8]}", daemon=True)

    def _run(self, sm: sessionmaker[DbSession], session_id: str, token: str, interval_s: float) -> None:
        while not self._stop.wait(interval_s):
            try:
                if not heartbeat(sm, session_id, token):
                    log.warning("session %s: claim %s lost while processing", session_id, token)
                    return
            except Exception:  # noqa: BLE001 - a missed heartbeat must not kill the job; the next one may work
                log.warning("session %s: heartbeat failed", session_id, exc_info=True)

    def __enter__(self) -> _Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def readable_error(exc: BaseException) -> str:
    """One line for the API: the exception's message (its type when that says more), never a traceback."""
    msg = " ".join(str(exc).split())
    if not msg:
        msg = type(exc).__name__
    elif not isinstance(exc, ValueError):
        msg = f"{type(exc).__name__}: {msg}"
    return msg[:MAX_ERROR_CHARS]


def _refresh_trends(db: DbSession, session_id: str) -> None:
    # --- trends hook (server.trends): keep per-session trend summaries in step with the strides. ---
    # Runs inside the transaction that writes the results, so trends never disagree with the strides.
    refresh_session(db, session_id)


def _clear_results(db: DbSession, session_id: str) -> None:
    db.execute(delete(Stride).where(Stride.session_id == session_id))
    db.execute(delete(KneeAngleTrace).where(KneeAngleTrace.session_id == session_id))


def _store_results(db: DbSession, sess_row: tuple[str, datetime], session_id: str,
                   result) -> tuple[int, int]:  # noqa: ANN001
    """Insert strides and traces; returns (stored, skipped). A stride with a non-finite metric is skipped: the
    columns are NOT NULL and SQLite would turn NaN into NULL (PostgreSQL would keep it), so keeping it would make
    the two databases disagree and the API emit invalid JSON."""
    patient_id, started_at = sess_row
    started_at = as_utc(started_at)
    stored = skipped = 0
    for leg, res in result.legs.items():
        for s in res.strides:
            values = {name: float(getattr(s, name)) for name in STORED_FLOATS}
            if not all(math.isfinite(v) for v in values.values()):
                skipped += 1
                continue
            db.add(Stride(
                session_id=session_id, patient_id=patient_id, leg=s.leg, index=s.index,
                started_at=started_at + timedelta(seconds=values["t_start_s"]), estimator=s.estimator,
                activity=StrideActivity(s.activity), fallback=bool(s.fallback),
                quality_reasons=list(s.quality_reasons), **values,
            ))
            stored += 1
        enc = encode_trace(res.t_s, res.angle_deg, res.estimator, res.fs_hz)
        db.add(KneeAngleTrace(
            session_id=session_id, leg=leg, t0_s=enc.t0_s, fs_hz=enc.fs_hz, n=enc.n, angle_deg=enc.angle_deg,
            estimator_codes=enc.estimator_codes, estimator_names=enc.estimator_names,
        ))
    return stored, skipped


def _default_processor(streams, activity: str, calibration=None):  # noqa: ANN001, ANN202
    from pipeline.long_sessions import process_source
    from pipeline.session import process_session
    from server.sessions.rawdata import StoredStreams

    if isinstance(streams, StoredStreams):  # longer than one chunk: read and processed window by window
        return process_source(streams, activity=activity, calibration=calibration, chunking=streams.chunking)
    return process_session(streams, activity=activity, calibration=calibration)


# Tests substitute a processor to exercise failure paths; production always uses the pipeline. Called as
# ``processor(streams, activity=..., calibration=...)`` (calibration: leg -> pipeline.types.KneeCalibration).
Processor = Callable[..., object]


def process_claimed(sm: sessionmaker[DbSession], session_id: str, token: str, *,
                    heartbeat_s: float = DEFAULT_HEARTBEAT_S, processor: Processor | None = None,
                    max_session_s: float | None = None) -> str:
    """Process a session this runner has claimed. Returns "done", "failed", "interrupted" (queued again: the
    database was unavailable) or "lost" (claim taken over).

    A session whose batches would ask for an absurd processing grid (:mod:`server.sessions.bounds`) fails with
    the reason before any sample is decoded.
    """
    from server.config import get_settings
    from server.sessions.bounds import session_span_problem
    from server.sessions.rawdata import input_counts, load_input

    if max_session_s is None:
        max_session_s = get_settings().max_session_s

    processor = processor or _default_processor
    t_start = time.perf_counter()
    with _Heartbeat(sm, session_id, token, heartbeat_s):
        try:
            with sm() as db:
                sess = db.get(Session, session_id)
                if sess is None:
                    return "lost"  # deleted meanwhile
                sess_row = (sess.patient_id, sess.started_at)
                activity = sess.activity
                # The calibration valid at the session's start, read now: a reprocess applies the current one.
                calibration = calibrations.applicable(db, sess.patient_id, sess.started_at)
                problem = session_span_problem(db, session_id, max_session_s)
                if problem is not None:
                    raise ValueError(f"not processed: {problem}")
                streams = load_input(sm, db, session_id)  # all streams, or windows of a long session
            n_sensors, n_samples, sensor_legs = input_counts(streams)
            result = processor(streams, activity=activity, calibration=calibrations.for_pipeline(calibration))
            with sm() as db:
                # The conditional update comes first: it locks the row, so a recovery cannot interleave.
                changed = _update(db, session_id, Session.worker_id == token,
                                  Session.status == SessionStatus.processing,
                                  status=SessionStatus.done, error=None, algorithm_version=result.algorithm_version,
                                  processed_at=utcnow(), heartbeat_at=None)
                if changed != 1:
                    db.rollback()
                    log.warning("session %s: claim %s lost before storing results; discarded", session_id, token)
                    return "lost"
                _clear_results(db, session_id)
                n_strides, n_skipped = _store_results(db, sess_row, session_id, result)
                summary = result.summary()
                summary[calibrations.SUMMARY_KEY] = calibrations.used_block(calibration, sensor_legs)
                if n_skipped:
                    summary.setdefault("warnings", []).append(
                        f"{n_skipped} stride(s) without finite metrics were not stored")
                    log.warning("session %s: %d stride(s) with non-finite metrics skipped", session_id, n_skipped)
                _update(db, session_id, summary=json_safe(summary))
                _refresh_trends(db, session_id)
                db.commit()
        except DB_UNAVAILABLE as exc:
            # The data are intact and the pipeline did not object: an interruption, not a failure.
            log.warning("session %s: database unavailable while processing (%s); queued again", session_id,
                        readable_error(exc))
            return _release(sm, session_id, token)
        except Exception as exc:  # noqa: BLE001 - any failure of one session must end as "failed", never crash
            log.error("session %s failed: %s\n%s", session_id, readable_error(exc), traceback.format_exc())
            return _mark_failed(sm, session_id, token, readable_error(exc))
    log.info("session %s done: %d sensors, %d samples, %d strides, %.2f s (%s)", session_id, n_sensors,
             n_samples, n_strides, time.perf_counter() - t_start, token)
    return "done"


def interrupted_error(times: int) -> str:
    """The error of a session failed after :data:`MAX_INTERRUPTIONS` interruptions."""
    return (f"processing was interrupted {times} times (worker killed, frozen or out of memory, or the database "
            "unavailable) without the pipeline reporting an error; the raw data are intact: reprocess to try again")


def _release(sm: sessionmaker[DbSession], session_id: str, token: str) -> str:
    """Give an interrupted claim back (status "queued"), or fail the session at the interruption cap; "lost" when
    the claim was no longer ours. If the database is still away the claim stays and the stall recovery releases
    it later (the same kind of interruption)."""
    mine = (Session.worker_id == token, Session.status == SessionStatus.processing)
    try:
        with sm() as db:
            changed = _update(db, session_id, *mine, Session.attempts < MAX_INTERRUPTIONS,
                              status=SessionStatus.queued, worker_id=None, heartbeat_at=None)
            db.commit()
        if changed == 1:
            return "interrupted"
        return _mark_failed(sm, session_id, token, interrupted_error(MAX_INTERRUPTIONS))
    except DB_UNAVAILABLE:
        log.warning("session %s: claim %s left to the stall recovery", session_id, token)
        return "interrupted"


def _mark_failed(sm: sessionmaker[DbSession], session_id: str, token: str, error: str) -> str:
    with sm() as db:
        changed = _update(db, session_id, Session.worker_id == token, Session.status == SessionStatus.processing,
                          status=SessionStatus.failed, error=error, processed_at=utcnow(), heartbeat_at=None)
        if changed != 1:
            db.rollback()
            return "lost"
        # Results of an earlier run no longer describe this session's state; the raw data stay for reprocess.
        _clear_results(db, session_id)
        _refresh_trends(db, session_id)
        db.commit()
    return "failed"


def process_one(sm: sessionmaker[DbSession], session_id: str, *, worker_id: str = "inline",
                heartbeat_s: float = DEFAULT_HEARTBEAT_S, processor: Processor | None = None) -> str:
    """Claim and process one session. Returns "done", "failed", "interrupted", "lost" or "skipped" (not queued /
    claimed)."""
    token = claim(sm, session_id, worker_id)
    if token is None:
        log.info("session %s not claimable (not queued or taken by another worker); skipped", session_id)
        return "skipped"
    log.info("session %s claimed by %s", session_id, token)
    t0 = time.perf_counter()
    outcome = process_claimed(sm, session_id, token, heartbeat_s=heartbeat_s, processor=processor)
    ops_metrics.job_finished(outcome, time.perf_counter() - t0)
    return outcome


def queued_ids(sm: sessionmaker[DbSession], limit: int = 100) -> list[str]:
    """Queued sessions, oldest completion first."""
    with sm() as db:
        stmt = (select(Session.id).where(Session.status == SessionStatus.queued)
                .order_by(Session.completed_at, Session.created_at).limit(limit))
        return list(db.scalars(stmt).all())


def run_queued(sm: sessionmaker[DbSession], *, worker_id: str = "inline", processor: Processor | None = None,
               should_stop: Callable[[], bool] | None = None, heartbeat_s: float = DEFAULT_HEARTBEAT_S) -> int:
    """Claim and process every queued session synchronously; returns how many this call processed."""
    count = 0
    interrupted: set[str] = set()  # queued again by this call: left to the next one (the database may be away)
    while True:
        progressed = False
        for sid in queued_ids(sm):
            if should_stop is not None and should_stop():
                return count
            if sid in interrupted:
                continue
            outcome = process_one(sm, sid, worker_id=worker_id, processor=processor, heartbeat_s=heartbeat_s)
            if outcome == "interrupted":
                interrupted.add(sid)
            if outcome != "skipped":
                count += 1
                progressed = True
        if not progressed:
            return count


def recover_stalled(sm: sessionmaker[DbSession], *, stall_seconds: float, everything: bool = False,
                    orphaned: Callable[[str], bool] | None = None) -> list[str]:
    """Put sessions stuck in "processing" back to "queued"; returns their ids (the caller enqueues them).

    Stuck means: heartbeat older than ``stall_seconds`` (its worker died), a claim token that ``orphaned`` says
    belongs to a worker known to be gone, or, with ``everything``, any processing session. A session
    interrupted :data:`MAX_INTERRUPTIONS` times is marked failed instead, with the reason.
    """
    cutoff = utcnow() - timedelta(seconds=stall_seconds)
    stale = [Session.status == SessionStatus.processing]
    if not everything and orphaned is None:
        stale.append(or_(Session.heartbeat_at.is_(None), Session.heartbeat_at < cutoff))
    with sm() as db:
        rows = db.execute(select(Session.id, Session.attempts, Session.worker_id, Session.heartbeat_at)
                          .where(*stale)).all()
        if not everything and orphaned is not None:
            rows = [r for r in rows if r.heartbeat_at is None or as_utc(r.heartbeat_at) < cutoff
                    or (r.worker_id is not None and orphaned(r.worker_id))]
        rows = [(r.id, r.attempts, r.worker_id) for r in rows]
        requeued: list[str] = []
        for sid, attempts, old_worker in rows:
            # Conditioned on the same claim so a worker that heart-beats right now keeps its session.
            same_claim = [Session.status == SessionStatus.processing, Session.worker_id == old_worker]
            if (attempts or 0) >= MAX_INTERRUPTIONS:
                err = interrupted_error(attempts)
                if _update(db, sid, *same_claim, status=SessionStatus.failed, error=err, worker_id=None,
                           heartbeat_at=None):
                    log.error("session %s: %s", sid, err)
                continue
            if _update(db, sid, *same_claim, status=SessionStatus.queued, worker_id=None, heartbeat_at=None):
                log.warning("session %s: processing by %s stalled; queued again", sid, old_worker)
                requeued.append(sid)
        db.commit()
    return requeued
