"""Storing uploaded batches idempotently, and what a session has received so far (counts and gaps).

Idempotency key: (session, sensor_id, seq). The content is compared by :func:`server.codec.content_sha256` of
the parsed values, so a replay that differs only in JSON formatting or compression is the same batch.

The hot path is one statement (:func:`insert_batch`): the session's status, the caller's access and the unique key
are checked by the INSERT itself; the stored batch is read back only when nothing was inserted.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from sqlalchemy import ColumnElement, Connection, Executable, bindparam, select, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.orm import Session as DbSession

from pipeline.params import WALKING
from server.codec import content_sha256, encode_samples
from server.enums import SessionStatus
from server.errors import conflict, invalid, not_found
from server.sessions.models import Batch, Session, SessionSensor
from server.sessions.schemas import BatchIn
from server.utc import utcnow

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
    if steps.size >= 3 and (median := _median(steps)) < 0.5 * period_ms:
        raise invalid("timestamps_ms", f"median spacing {median:.3g} ms is less than half the "
                                       f"declared sample period ({period_ms:.3g} ms at {sample_rate_hz:g} Hz)")
    if abs(float(t_ms[0]) - t0_ms) > period_ms:
        raise invalid("t0_ms", f"t0_ms ({t0_ms}) must be the time of the first sample (timestamps_ms[0] = "
                               f"{float(t_ms[0])})")


def _median(x: np.ndarray) -> float:
    """``np.median`` of a finite 1-D array, the same value from one partition: np.median's generic reduction
    machinery cost ~0.08 ms per batch, more than the timestamps' other checks together."""
    k = x.size // 2
    if x.size % 2:
        return float(np.partition(x, k)[k])
    part = np.partition(x, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2)


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


@dataclass(frozen=True)
class PreparedBatch:
    """A validated batch in its stored form (what the INSERT writes)."""

    sensor_id: str
    seq: int
    t0_ms: float
    n_samples: int
    t_first_ms: float
    t_last_ms: float
    content_sha256: str
    t_ms: bytes
    gyro: bytes
    acc: bytes


def sensor_rates(session: Session) -> dict[str, float]:
    """The declared sensors of a session and their sample rates (Hz)."""
    return {s.sensor_id: s.sample_rate_hz for s in session.sensors}


def prepare_batch(rates_hz: dict[str, float], body: BatchIn, *, max_samples: int) -> PreparedBatch:
    """Validate a batch against its session's declared sensors (422 problems) and encode it for storage."""
    rate_hz = rates_hz.get(body.sensor_id)
    if rate_hz is None:
        declared = ", ".join(sorted(rates_hz))
        raise invalid("sensor_id", f"sensor {body.sensor_id!r} is not declared for this session ({declared})")
    n = len(body.gyro)
    if n > max_samples:
        raise invalid("gyro", f"{n} samples exceed the limit of {max_samples} per batch")
    t_ms = sample_times_ms(body, rate_hz)
    validate_times(t_ms, body.t0_ms, rate_hz)
    gyro = np.asarray(body.gyro, dtype=np.float64)
    acc = np.asarray(body.acc, dtype=np.float64)
    t_b, g_b, a_b = encode_samples(t_ms, gyro, acc)
    return PreparedBatch(sensor_id=body.sensor_id, seq=body.seq, t0_ms=body.t0_ms, n_samples=n,
                         t_first_ms=float(t_ms[0]), t_last_ms=float(t_ms[-1]),
                         content_sha256=content_sha256(t_ms, gyro, acc), t_ms=t_b, gyro=g_b, acc=a_b)


_INSERTED_COLUMNS = ("sensor_id", "seq", "t0_ms", "n_samples", "t_first_ms", "t_last_ms", "content_sha256", "t_ms",
                     "gyro", "acc", "created_at")


def guarded_insert(dialect: str, guards: Sequence[ColumnElement[bool]] = ()) -> Executable:
    """``INSERT INTO batches SELECT <values> FROM sessions WHERE id = :b_session_id AND status = 'receiving' AND
    <guards> [FOR SHARE] ON CONFLICT DO NOTHING RETURNING id``: the status check, the caller's checks and the
    store in one statement. Values are bound by name (:func:`insert_params`), so the statement is built once."""
    cols = Batch.__table__.c
    values = [Session.id, *(bindparam(f"b_{c}", type_=cols[c].type) for c in _INSERTED_COLUMNS)]
    source = select(*values).where(Session.id == bindparam("b_session_id"),
                                   Session.status == SessionStatus.receiving, *guards)
    if dialect == "postgresql":
        # A share lock for the instant of the insert: a /complete (FOR UPDATE, then its status write) either
        # committed before, and the re-checked row is no longer "receiving" (nothing inserted), or waits for this
        # commit and counts the batch. Uploads of the session's other sensors share the lock.
        source = source.with_for_update(read=True, of=Session)
        insert = pg_insert
    else:
        # SQLite takes the database write lock when the INSERT starts, before it reads the session row.
        insert = sqlite_insert
    return (insert(Batch).from_select([cols.session_id, *(cols[c] for c in _INSERTED_COLUMNS)], source)
            .on_conflict_do_nothing(index_elements=[cols.session_id, cols.sensor_id, cols.seq])
            .returning(cols.id))


def insert_params(session_id: str, p: PreparedBatch) -> dict[str, object]:
    """The values :func:`guarded_insert` binds."""
    return {"b_session_id": session_id, "b_sensor_id": p.sensor_id, "b_seq": p.seq, "b_t0_ms": p.t0_ms,
            "b_n_samples": p.n_samples, "b_t_first_ms": p.t_first_ms, "b_t_last_ms": p.t_last_ms,
            "b_content_sha256": p.content_sha256, "b_t_ms": p.t_ms, "b_gyro": p.gyro, "b_acc": p.acc,
            "b_created_at": utcnow()}


_UNGUARDED: dict[str, Executable] = {}


def insert_batch(conn: Connection, stmt: Executable, params: dict[str, object]) -> bool:
    """Run a :func:`guarded_insert`; True when it stored the batch. The caller commits, or runs it on an
    autocommit connection (then the 201 it allows is durable when this returns)."""
    return bool(conn.execute(stmt, params).all())


def _find_batch(db: DbSession, session_id: str, sensor_id: str, seq: int) -> tuple[str, int] | None:
    row = db.execute(select(Batch.content_sha256, Batch.n_samples).where(
        Batch.session_id == session_id, Batch.sensor_id == sensor_id, Batch.seq == seq)).first()
    return None if row is None else (row[0], row[1])


def explain_refusal(db: DbSession, session_id: str, p: PreparedBatch) -> IngestOutcome | None:
    """Why a guarded insert stored nothing: an identical replay (outcome), other content or a session that is not
    receiving (409); None when neither holds (a guard failed, or the conflicting row was gone again)."""
    # A retry of a batch whose answer was lost stays a 200 (or 409 for other content) even after /complete, so
    # the app never mistakes a stored batch for a lost one; only NEW batches need a receiving session.
    existing = _find_batch(db, session_id, p.sensor_id, p.seq)
    if existing is not None:
        db.rollback()
        if existing[0] != p.content_sha256:
            raise conflict(f"Batch seq {p.seq} of sensor {p.sensor_id!r} was already received with "
                           f"different content", slug="batch-conflict")
        return IngestOutcome(created=False, sensor_id=p.sensor_id, seq=p.seq, samples=existing[1])
    status = db.scalar(select(Session.status).where(Session.id == session_id))
    db.rollback()
    if status is not None and status != SessionStatus.receiving:
        raise conflict(f"Session is {status}; uploads are accepted only while it is receiving",
                       slug="session-not-receiving")
    return None


def ingest_batch(db: DbSession, session: Session, body: BatchIn, *, max_samples: int) -> IngestOutcome:
    """Validate and store one batch of a session the caller may write to, committed before returning (the 201
    means the data is durable). A rejected batch raises :class:`ProblemError` and changes nothing.

    The status is checked by the insert itself, so a stale ``session`` object cannot let a batch in after a
    concurrent /complete committed.
    """
    p = prepare_batch(sensor_rates(session), body, max_samples=max_samples)
    dialect = db.get_bind().dialect.name
    stmt = _UNGUARDED.get(dialect)
    if stmt is None:
        stmt = _UNGUARDED[dialect] = guarded_insert(dialect)
    if insert_batch(db.connection(), stmt, insert_params(session.id, p)):
        db.commit()
        return IngestOutcome(created=True, sensor_id=p.sensor_id, seq=p.seq, samples=p.n_samples)
    db.rollback()
    outcome = explain_refusal(db, session.id, p)
    if outcome is None:
        raise not_found("Session")  # deleted between the read of ``session`` and the insert
    return outcome


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

