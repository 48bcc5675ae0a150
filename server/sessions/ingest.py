"""Storing uploaded batches idempotently, and what a session has received so far (counts and gaps).

Idempotency key: (session, sensor_id, seq). The content is compared by :func:`server.codec.content_sha256` of
the parsed values, so a replay that differs only in JSON formatting or compression is the same batch.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session as DbSession

from pipeline.params import WALKING
from server.codec import content_sha256, encode_samples
from server.enums import SessionStatus
from server.errors import conflict, invalid
from server.sessions.models import Batch, Session, SessionSensor
from server.sessions.schemas import BatchIn

log = logging.getLogger("gaitmon.ingest")

# A step between consecutive samples longer than this many sample periods is a gap.
MAX_LISTED_MISSING_SEQ = 100


@dataclass(frozen=True)
class IngestOutcome:
    """What storing a batch did: stored, or an identical replay."""

    created: bool  # False: identical replay of a stored batch
    sensor_id: str
    seq: int
    samples: int


def sample_times_ms(body: BatchIn, sample_rate_hz: float) -> np.ndarray:
    """The batch's sample times in ms: the explicit timestamps, else t0 + i * period (contract)."""
    if body.timestamps_ms is not None:
        return np.asarray(body.timestamps_ms, dtype=np.float64)
    return body.t0_ms + np.arange(len(body.gyro), dtype=np.float64) * (1000.0 / sample_rate_hz)


def validate_times(t_ms: np.ndarray, t0_ms: float, sample_rate_hz: float) -> None:
    """Strictly increasing timestamps that start at ``t0_ms`` (within one sample period); else 422."""
    steps = np.diff(t_ms)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise invalid(f"timestamps_ms[{i}]", f"timestamps must be strictly increasing ({float(t_ms[i - 1])} then "
                                             f"{float(t_ms[i])})")
    period_ms = 1000.0 / sample_rate_hz
    # Half the declared period or less between most samples means the stamps (or the declared rate) are wrong;
    # the median tolerates the bunching of samples stamped on arrival of a BLE notification.
    if steps.size >= 3 and float(np.median(steps)) < 0.5 * period_ms:
        raise invalid("timestamps_ms", f"median spacing {float(np.median(steps)):.3g} ms is less than half the "
                                       f"declared sample period ({period_ms:.3g} ms at {sample_rate_hz:g} Hz)")
    if abs(float(t_ms[0]) - t0_ms) > period_ms:
        raise invalid("t0_ms", f"t0_ms ({t0_ms}) must be the time of the first sample (timestamps_ms[0] = "
                               f"{float(t_ms[0])})")


def still_in_status(db: DbSession, session_id: str, statuses: tuple[str, ...]) -> bool:
    """Lock the session row for writing if its status is one of ``statuses``; False if it is not.

    A no-op UPDATE is the portable way to lock: SQLite has no SELECT ... FOR UPDATE, and pysqlite starts the
    transaction only at the first write.
    """
    result = db.execute(
        update(Session).where(Session.id == session_id, Session.status.in_(statuses))
        .values(status=Session.status).execution_options(synchronize_session=False)
    )
    return result.rowcount == 1


def _find_batch(db: DbSession, session_id: str, sensor_id: str, seq: int) -> Batch | None:
    return db.scalar(select(Batch).where(Batch.session_id == session_id, Batch.sensor_id == sensor_id,
                                         Batch.seq == seq))


def _replay_outcome(existing: Batch, digest: str) -> IngestOutcome:
    if existing.content_sha256 != digest:
        raise conflict(f"Batch seq {existing.seq} of sensor {existing.sensor_id!r} was already received with "
                       f"different content", slug="batch-conflict")
    return IngestOutcome(created=False, sensor_id=existing.sensor_id, seq=existing.seq, samples=existing.n_samples)


def ingest_batch(db: DbSession, session: Session, body: BatchIn, *, max_samples: int) -> IngestOutcome:
    """Validate and store one batch, committed before returning (the 201 means the data is durable).

    ``session`` should be read with a row lock so a concurrent /complete cannot slip in between the status
    check and the insert. A rejected batch raises :class:`ProblemError` and changes nothing.
    """
    sensor = next((s for s in session.sensors if s.sensor_id == body.sensor_id), None)
    if sensor is None:
        declared = ", ".join(s.sensor_id for s in session.sensors)
        raise invalid("sensor_id", f"sensor {body.sensor_id!r} is not declared for this session ({declared})")
    n = len(body.gyro)
    if n > max_samples:
        raise invalid("gyro", f"{n} samples exceed the limit of {max_samples} per batch")
    t_ms = sample_times_ms(body, sensor.sample_rate_hz)
    validate_times(t_ms, body.t0_ms, sensor.sample_rate_hz)
    gyro = np.asarray(body.gyro, dtype=np.float64)
    acc = np.asarray(body.acc, dtype=np.float64)
    digest = content_sha256(t_ms, gyro, acc)
    # A retry of a batch whose answer was lost stays a 200 (or 409 for other content) even after /complete, so
    # the app never mistakes a stored batch for a lost one; only NEW batches need a receiving session.
    existing = _find_batch(db, session.id, sensor.sensor_id, body.seq)
    if existing is not None:
        return _replay_outcome(existing, digest)
    if session.status != SessionStatus.receiving:
        raise conflict(f"Session is {session.status}; uploads are accepted only while it is receiving",
                       slug="session-not-receiving")

    # Re-check the status with a write in this transaction: on SQLite this takes the write lock (a SELECT does
    # not), on PostgreSQL the row lock, so a /complete either commits before (-> 409) or waits for this batch.
    if not still_in_status(db, session.id, (SessionStatus.receiving,)):
        db.rollback()
        raise conflict("Session was completed; uploads are accepted only while it is receiving",
                       slug="session-not-receiving")
    existing = _find_batch(db, session.id, sensor.sensor_id, body.seq)
    if existing is not None:
        db.rollback()
        return _replay_outcome(existing, digest)

    t_b, g_b, a_b = encode_samples(t_ms, gyro, acc)
    db.add(Batch(session_id=session.id, sensor_id=sensor.sensor_id, seq=body.seq, t0_ms=body.t0_ms, n_samples=n,
                 t_first_ms=float(t_ms[0]), t_last_ms=float(t_ms[-1]), content_sha256=digest,
                 t_ms=t_b, gyro=g_b, acc=a_b))
    try:
        db.commit()
    except IntegrityError:
        # The same (sensor, seq) was inserted concurrently: answer as for a replay.
        db.rollback()
        existing = _find_batch(db, session.id, sensor.sensor_id, body.seq)
        if existing is None:
            raise
        return _replay_outcome(existing, digest)
    return IngestOutcome(created=True, sensor_id=sensor.sensor_id, seq=body.seq, samples=n)


def _sensor_received(rows: list, fs_hz: float) -> dict:
    """Counts and gaps of one sensor from its batches' (seq, n_samples, t_first_ms, t_last_ms, t_ms) rows.

    Vectorised over all samples: an hour at 100 Hz in 50-sample batches is 7 200 rows per sensor.
    """
    if not rows:
        return {"batches": 0, "samples": 0, "gaps": 0, "gap_s": 0.0, "first_t_s": None, "last_t_s": None,
                "missing_seq": [], "observed_rate_hz": None}
    rows = sorted(rows, key=lambda r: r.seq)
    period_ms = 1000.0 / fs_hz
    limit = WALKING.prepare.gap_factor * period_ms  # the pipeline's rule, so received.gaps matches summary.gaps
    # Steps between consecutive samples inside each batch (the steps across batch boundaries are masked out).
    t = np.frombuffer(b"".join(r.t_ms for r in rows), dtype="<f8")
    steps = np.diff(t)
    inside = np.ones(len(steps), dtype=bool)
    ends = np.cumsum([r.n_samples for r in rows])[:-1] - 1
    inside[ends] = False
    jumps = steps[inside & (steps > limit)]
    gaps = int(jumps.size)
    gap_ms = float(np.sum(jumps - period_ms))
    # Boundaries in seq order: one gap per boundary, whether a missing seq, a time jump, or both.
    seq = np.array([r.seq for r in rows], dtype=np.int64)
    first = np.array([r.t_first_ms for r in rows])
    last = np.array([r.t_last_ms for r in rows])
    dt = first[1:] - last[:-1]
    boundary = (np.diff(seq) > 1) | (dt > limit)
    gaps += int(np.count_nonzero(boundary))
    gap_ms += float(np.sum(np.maximum(0.0, dt[boundary] - period_ms)))
    missing: list[int] = []
    for i in np.flatnonzero(np.diff(seq) > 1):
        missing.extend(range(int(seq[i]) + 1, min(int(seq[i + 1]), int(seq[i]) + 1 + MAX_LISTED_MISSING_SEQ)))
        if len(missing) >= MAX_LISTED_MISSING_SEQ:
            break
    return {
        "batches": len(rows),
        "samples": int(sum(r.n_samples for r in rows)),
        "gaps": gaps,
        "gap_s": round(gap_ms / 1000.0, 3),
        "first_t_s": float(first.min()) / 1000.0,
        "last_t_s": float(last.max()) / 1000.0,
        "missing_seq": missing[:MAX_LISTED_MISSING_SEQ],
        # From the median step inside batches: shows a declared rate that does not match the timestamps.
        "observed_rate_hz": round(1000.0 / float(np.median(steps[inside])), 2) if inside.any() else None,
    }


def received_summary(db: DbSession, session: Session) -> dict[str, dict]:
    """Per declared sensor: batches, samples, gaps (the pipeline's ``PrepareParams.gap_factor`` rule), gap_s,
    time span, missing seq."""
    rows = db.execute(
        select(Batch.sensor_id, Batch.seq, Batch.n_samples, Batch.t_first_ms, Batch.t_last_ms, Batch.t_ms)
        .where(Batch.session_id == session.id)
    ).all()
    by_sensor: dict[str, list] = {}
    for r in rows:
        by_sensor.setdefault(r.sensor_id, []).append(r)
    sensors: list[SessionSensor] = list(session.sensors)
    return {s.sensor_id: _sensor_received(by_sensor.get(s.sensor_id, []), s.sample_rate_hz) for s in sensors}

