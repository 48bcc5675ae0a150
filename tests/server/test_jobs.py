"""Job processing: exclusive claim, result storage and replacement, failures, stall recovery, the runners.

The processing step is injected where a test is about the job machinery rather than the algorithm: the
processor below derives its strides from the stored samples, so what the jobs store can be checked against
what the processor computed from what was uploaded.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from sqlalchemy import func, select, update
from sqlalchemy.exc import OperationalError

from pipeline.types import LegResult, SessionResult, StrideMetrics
from server.codec import content_sha256, decode_trace, encode_samples, encode_trace
from server.config import Settings
from server.db import make_engine, make_sessionmaker
from server.patients.models import Patient
from server.processing import jobs, queue
from server.processing.embedded import EmbeddedRunner
from server.results.models import KneeAngleTrace, Stride
from server.sessions.models import Batch, Session, SessionSensor

FS_HZ = 100.0
STARTED_AT = datetime(2026, 11, 21, 9, 30, tzinfo=UTC)


@pytest.fixture
def sm(settings: Settings):  # noqa: ANN201
    engine = make_engine(settings.resolved_database_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def make_session(sm, *, status: str = "queued", seconds: float = 6.0, seed: int = 0) -> str:  # noqa: ANN001
    """A patient with one left-leg session (thigh + shank, two batches each) in the given status."""
    rng = np.random.default_rng(seed)
    with sm() as db:
        patient = Patient(display_name="p")
        db.add(patient)
        db.flush()
        sess = Session(patient_id=patient.id, client_session_id=f"c{seed}-{rng.integers(1 << 30)}",
                       started_at=STARTED_AT, activity="walking", status=status)
        db.add(sess)
        db.flush()
        n = int(seconds * FS_HZ)
        for sensor_id, segment in (("L-thigh", "thigh"), ("L-shank", "shank")):
            db.add(SessionSensor(session_id=sess.id, sensor_id=sensor_id, leg="left", segment=segment,
                                 sample_rate_hz=FS_HZ, gyro_unit="deg/s", acc_unit="m/s2"))
            t_ms = np.arange(n) * 1000.0 / FS_HZ
            gyro = 200.0 * np.sin(2 * np.pi * t_ms / 1000.0)[:, None] + rng.normal(0, 1, (n, 3))
            acc = np.tile([0.0, 0.0, 9.81], (n, 1)) + rng.normal(0, 0.1, (n, 3))
            for seq, part in enumerate(np.array_split(np.arange(n), 2)):
                tb, gb, ab = encode_samples(t_ms[part], gyro[part], acc[part])
                db.add(Batch(session_id=sess.id, sensor_id=sensor_id, seq=seq, t0_ms=float(t_ms[part][0]),
                             n_samples=len(part), t_first_ms=float(t_ms[part][0]),
                             t_last_ms=float(t_ms[part][-1]),
                             content_sha256=content_sha256(t_ms[part], gyro[part], acc[part]),
                             t_ms=tb, gyro=gb, acc=ab))
        db.commit()
        return sess.id


def data_processor(stride_s: float = 1.0, version: str = "test-1",
                   nan_peaks: bool = False) -> Callable[..., SessionResult]:
    """Strides of ``stride_s`` over the shank data; the angle is |shank gyro x| (data-derived, not canned)."""

    def run(streams, activity: str, calibration=None) -> SessionResult:  # noqa: ANN001
        shank = next(s for s in streams if s.segment == "shank")
        angle = np.abs(shank.gyr[:, 0]) / 10.0
        est = np.where(np.arange(len(angle)) % 2 == 0, "go", "cf")
        strides = []
        starts = np.arange(shank.t_s[0], shank.t_s[-1] - stride_s, stride_s)
        for i, t0 in enumerate(starts):
            win = (shank.t_s >= t0) & (shank.t_s < t0 + stride_s)
            strides.append(StrideMetrics(
                leg="left", index=i, t_start_s=float(t0), t_end_s=float(t0 + stride_s), duration_s=stride_s,
                t_toe_off_s=float(t0 + 0.6 * stride_s), stance_time_s=0.6 * stride_s,
                swing_time_s=0.4 * stride_s, stance_pct=60.0,
                peak_swing_flexion_deg=float("nan") if nan_peaks and i == 1 else float(angle[win].max()),
                min_flexion_deg=float(angle[win].min()), rom_deg=float(np.ptp(angle[win])),
                stance_flexion_deg=float(angle[win][0]), estimator="go", quality=1.0, quality_reasons=("ok",),
            ))
        leg = LegResult(leg="left", fs_hz=shank.fs_hz, t_s=shank.t_s, angle_deg=angle, estimator=est,
                        strides=strides, walking_s=float(shank.t_s[-1]))
        return SessionResult(algorithm_version=version, activity=activity, legs={"left": leg})

    return run


def failing_processor(streams, activity: str, calibration=None) -> SessionResult:  # noqa: ANN001
    raise ValueError("no shank sensor data for leg left:\n  check the sensor placement")


def n_strides(sm, sid: str) -> int:  # noqa: ANN001
    with sm() as db:
        return db.scalar(select(func.count()).select_from(Stride).where(Stride.session_id == sid))


def get(sm, sid: str) -> Session:  # noqa: ANN001
    with sm() as db:
        return db.get(Session, sid)


def test_claim_is_exclusive(sm) -> None:  # noqa: ANN001
    sid = make_session(sm)
    first = jobs.claim(sm, sid, "a")
    second = jobs.claim(sm, sid, "b")
    assert first is not None and first.startswith("a:")
    assert second is None
    row = get(sm, sid)
    assert (row.status, row.worker_id, row.attempts) == ("processing", first, 1)
    assert row.heartbeat_at is not None


def test_concurrent_claims_one_winner(sm) -> None:  # noqa: ANN001
    sid = make_session(sm)
    barrier = threading.Barrier(6)
    wins: list[str | None] = []

    def claimer(i: int) -> None:
        barrier.wait()
        wins.append(jobs.claim(sm, sid, f"w{i}"))

    threads = [threading.Thread(target=claimer, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(wins) == 6
    assert sum(w is not None for w in wins) == 1
    assert get(sm, sid).attempts == 1


def test_process_stores_strides_and_trace(sm) -> None:  # noqa: ANN001
    sid = make_session(sm, seconds=6.0)
    assert jobs.run_queued(sm, processor=data_processor()) == 1
    row = get(sm, sid)
    assert row.status == "done" and row.error is None and row.algorithm_version == "test-1"
    assert row.summary["legs"]["left"]["n_strides"] == 5
    assert row.worker_id.startswith("inline:")
    with sm() as db:
        strides = db.scalars(select(Stride).where(Stride.session_id == sid).order_by(Stride.index)).all()
        trace = db.get(KneeAngleTrace, (sid, "left"))
    assert [s.index for s in strides] == list(range(5))
    for s in strides:
        started = s.started_at if s.started_at.tzinfo else s.started_at.replace(tzinfo=UTC)
        assert started == STARTED_AT + timedelta(seconds=s.t_start_s)
        assert s.patient_id == row.patient_id
    assert strides[2].peak_swing_flexion_deg > 15.0  # |200 sin| / 10 peaks near 20 deg in every second
    t, angle, est = decode_trace(trace.t0_s, trace.fs_hz, trace.n, trace.angle_deg, trace.estimator_codes,
                                 trace.estimator_names)
    assert trace.n == 600 and t[1] - t[0] == pytest.approx(0.01)
    assert set(est) == {"go", "cf"}
    assert np.nanmax(angle) == pytest.approx(max(s.peak_swing_flexion_deg for s in strides), abs=0.5)


def test_trend_summaries_follow_the_results(sm) -> None:  # noqa: ANN001
    from server.trends.models import TrendSessionLeg

    def legs(sid: str) -> list[tuple[str, int]]:
        with sm() as db:
            rows = db.scalars(select(TrendSessionLeg).where(TrendSessionLeg.session_id == sid)).all()
            return [(r.leg, r.n_strides) for r in rows]

    sid = make_session(sm)
    jobs.run_queued(sm, processor=data_processor())
    assert legs(sid) == [("left", 5)]
    with sm() as db:
        db.execute(update(Session).where(Session.id == sid).values(status="queued"))
        db.commit()
    jobs.run_queued(sm, processor=failing_processor)
    assert legs(sid) == []  # a failed run leaves nothing in the trends


def test_non_finite_values_never_reach_the_database(sm) -> None:  # noqa: ANN001
    sid = make_session(sm)
    jobs.run_queued(sm, processor=data_processor(nan_peaks=True))
    row = get(sm, sid)
    assert row.status == "done", row.error
    # The pipeline's own summary has a NaN median; stored JSON has null, the same on SQLite and PostgreSQL.
    assert row.summary["legs"]["left"]["peak_swing_flexion_deg_median"] is None
    assert row.summary["legs"]["left"]["rom_deg_median"] > 0
    assert "1 stride(s) without finite metrics were not stored" in row.summary["warnings"]
    with sm() as db:
        indices = db.scalars(select(Stride.index).where(Stride.session_id == sid).order_by(Stride.index)).all()
    assert indices == [0, 2, 3, 4]


def test_reprocess_replaces_results(sm) -> None:  # noqa: ANN001
    sid = make_session(sm, seconds=6.0)
    jobs.run_queued(sm, processor=data_processor(stride_s=1.0))
    assert n_strides(sm, sid) == 5
    # What the reprocess endpoint does: back to queued, then the runner goes again.
    with sm() as db:
        db.execute(update(Session).where(Session.id == sid).values(status="queued", error=None))
        db.commit()
    assert jobs.run_queued(sm, processor=data_processor(stride_s=0.5, version="test-2")) == 1
    assert n_strides(sm, sid) == 11
    row = get(sm, sid)
    assert (row.status, row.algorithm_version, row.attempts) == ("done", "test-2", 2)
    with sm() as db:
        assert db.scalar(select(func.count()).select_from(KneeAngleTrace)
                         .where(KneeAngleTrace.session_id == sid)) == 1


def test_failure_is_readable_and_clears_old_results(sm) -> None:  # noqa: ANN001
    sid = make_session(sm)
    other = make_session(sm, seed=1)
    jobs.run_queued(sm, processor=data_processor())
    assert n_strides(sm, sid) == 5
    with sm() as db:
        db.execute(update(Session).where(Session.id == sid).values(status="queued"))
        db.commit()
    assert jobs.run_queued(sm, processor=failing_processor) == 1
    row = get(sm, sid)
    assert row.status == "failed"
    assert row.error == "no shank sensor data for leg left: check the sensor placement"
    assert "Traceback" not in row.error and "\n" not in row.error
    assert n_strides(sm, sid) == 0
    assert get(sm, other).status == "done" and n_strides(sm, other) == 5  # other sessions untouched


def test_session_without_data_fails_in_the_real_path(sm) -> None:  # noqa: ANN001
    """No processor injected: whatever the production path raises on an empty session ends as "failed"."""
    sid = make_session(sm)
    with sm() as db:
        db.query(Batch).filter(Batch.session_id == sid).delete()
        db.commit()
    assert jobs.run_queued(sm) == 1
    row = get(sm, sid)
    assert row.status == "failed"
    assert row.error and "\n" not in row.error and len(row.error) <= jobs.MAX_ERROR_CHARS


def test_stalled_processing_is_recovered(sm) -> None:  # noqa: ANN001
    stale = make_session(sm, seed=1)
    live = make_session(sm, seed=2)
    for sid in (stale, live):
        assert jobs.claim(sm, sid, "dead-worker")
    with sm() as db:
        db.execute(update(Session).where(Session.id == stale)
                   .values(heartbeat_at=datetime.now(UTC) - timedelta(seconds=600)))
        db.commit()
    assert jobs.recover_stalled(sm, stall_seconds=300) == [stale]
    assert get(sm, stale).status == "queued" and get(sm, stale).worker_id is None
    assert get(sm, live).status == "processing"  # fresh heartbeat: still owned by its worker
    assert jobs.run_queued(sm, processor=data_processor()) == 1
    assert get(sm, stale).status == "done" and get(sm, stale).attempts == 2
    # Single-process start-up: every processing session is orphaned.
    assert jobs.recover_stalled(sm, stall_seconds=300, everything=True) == [live]


def test_interrupted_three_times_is_still_processed(sm) -> None:  # noqa: ANN001
    """Workers killed mid-session three times (the old cap) and more: the intact data are processed."""
    sid = make_session(sm)
    for _ in range(4):
        assert jobs.claim(sm, sid, "killed")
        assert jobs.recover_stalled(sm, stall_seconds=0, everything=True) == [sid]
    assert get(sm, sid).status == "queued"
    assert jobs.run_queued(sm, processor=data_processor()) == 1
    row = get(sm, sid)
    assert (row.status, row.error, row.attempts) == ("done", None, 5) and n_strides(sm, sid) == 5


def test_crash_loop_ends_failed_saying_why(sm) -> None:  # noqa: ANN001
    sid = make_session(sm)
    for i in range(jobs.MAX_INTERRUPTIONS):
        assert jobs.claim(sm, sid, "crashing")
        expected = [sid] if i < jobs.MAX_INTERRUPTIONS - 1 else []
        assert jobs.recover_stalled(sm, stall_seconds=0, everything=True) == expected
    row = get(sm, sid)
    assert row.status == "failed" and row.error == jobs.interrupted_error(jobs.MAX_INTERRUPTIONS)
    assert f"interrupted {jobs.MAX_INTERRUPTIONS} times" in row.error and "intact" in row.error


def _database_away(streams, activity: str, calibration=None) -> SessionResult:  # noqa: ANN001
    raise OperationalError("SELECT 1", {}, Exception("connection to server was lost"))


def test_database_errors_interrupt_and_pipeline_errors_fail(sm) -> None:  # noqa: ANN001
    """An unavailable database is an interruption (queued again, up to the cap); a pipeline error is final."""
    sid = make_session(sm)
    assert jobs.process_one(sm, sid, processor=_database_away) == "interrupted"
    assert (get(sm, sid).status, get(sm, sid).worker_id) == ("queued", None)
    # run_queued leaves a session it saw interrupted to its next call instead of spinning on it.
    assert jobs.run_queued(sm, processor=_database_away) == 1
    assert get(sm, sid).status == "queued" and get(sm, sid).attempts == 2
    assert jobs.run_queued(sm, processor=data_processor()) == 1
    assert get(sm, sid).status == "done" and n_strides(sm, sid) == 5
    capped = make_session(sm, seed=3)
    outcomes = [jobs.process_one(sm, capped, processor=_database_away) for _ in range(jobs.MAX_INTERRUPTIONS)]
    assert outcomes == ["interrupted"] * (jobs.MAX_INTERRUPTIONS - 1) + ["failed"]
    assert get(sm, capped).error == jobs.interrupted_error(jobs.MAX_INTERRUPTIONS)
    broken = make_session(sm, seed=4)
    assert jobs.process_one(sm, broken, processor=failing_processor) == "failed"
    assert get(sm, broken).attempts == 1 and "sensor placement" in get(sm, broken).error


def test_worker_that_lost_its_claim_stores_nothing(sm) -> None:  # noqa: ANN001
    sid = make_session(sm)
    slow_token = jobs.claim(sm, sid, "slow")
    # The slow worker is presumed dead, the session recovered and finished by another worker...
    assert jobs.recover_stalled(sm, stall_seconds=0, everything=True) == [sid]
    assert jobs.run_queued(sm, worker_id="fast", processor=data_processor(stride_s=1.0)) == 1
    # ...then the slow one finishes: its results are discarded, the fast one's stay.
    outcome = jobs.process_claimed(sm, sid, slow_token, processor=data_processor(stride_s=0.5))
    assert outcome == "lost"
    assert n_strides(sm, sid) == 5
    assert get(sm, sid).worker_id.startswith("fast:")


def test_trace_encoding_places_gaps_on_the_grid() -> None:
    t = np.r_[np.arange(0, 1, 0.01), np.arange(1.5, 2, 0.01)] + 3.0
    angle = np.linspace(0, 60, len(t))
    est = np.array(["go"] * 100 + ["cf"] * 50)
    enc = encode_trace(t, angle, est, 100.0)
    assert enc.n == 200 and enc.estimator_names == ["", "cf", "go"]
    t2, a2, e2 = decode_trace(enc.t0_s, enc.fs_hz, enc.n, enc.angle_deg, enc.estimator_codes, enc.estimator_names)
    assert np.all(np.isnan(a2[100:150])) and set(e2[100:150]) == {""}
    assert np.allclose(a2[150:], angle[100:], atol=1e-4) and np.allclose(t2[150:], t[100:])
    with pytest.raises(ValueError):
        encode_trace(np.array([0.0, 0.001]), np.zeros(2), np.array(["go", "go"]), 100.0)


def test_embedded_runner_wakes_on_enqueue_and_recovers_at_start(settings: Settings, sm,  # noqa: ANN001
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(jobs, "_default_processor", data_processor())
    orphan = make_session(sm, seed=1)
    assert jobs.claim(sm, orphan, "killed-api")  # left "processing" by a killed API process
    # A long poll interval: only the wake-up by enqueue can make the runner react quickly.
    runner = EmbeddedRunner(sm, settings, recover_all_at_start=True, poll_s=30.0).start()
    try:
        deadline = time.monotonic() + 20
        while get(sm, orphan).status != "done" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert get(sm, orphan).status == "done"
        sid = make_session(sm, seed=2, status="queued")
        queue.enqueue(settings.model_copy(update={"job_runner": "embedded"}), sid)
        deadline = time.monotonic() + 20
        while get(sm, sid).status != "done" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert get(sm, sid).status == "done" and n_strides(sm, sid) == 5
    finally:
        runner.stop()


@pytest.fixture
def pg_settings(postgres_url: str, tmp_path) -> Settings:  # noqa: ANN001
    from server.processing.worker import apply_schema
    from tests.conftest import _truncate_all

    apply_schema(postgres_url)
    _truncate_all(postgres_url)  # also empties procrastinate's tables: no jobs left over from other tests
    return Settings(database_url=postgres_url, data_dir=tmp_path / "data", job_runner="procrastinate")


def test_procrastinate_worker_processes_deferred_jobs_once(pg_settings: Settings,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The multi-machine path: the API defers to the PostgreSQL queue, a separate worker processes it."""
    from sqlalchemy import text

    from server.processing import worker

    monkeypatch.setattr(jobs, "_default_processor", data_processor())
    sm = make_sessionmaker(make_engine(pg_settings.resolved_database_url))
    url = pg_settings.resolved_database_url
    try:
        a, b = make_session(sm, seed=1), make_session(sm, seed=2)
        queue.enqueue(pg_settings, a)
        queue.enqueue(pg_settings, a)  # complete retried: the queueing lock keeps one waiting job
        queue.enqueue(pg_settings, b)
        # A duplicate delivery that bypasses the queueing lock (as after a job was presumed lost).
        worker._api_app(url).configure_task(worker.PROCESS_TASK).defer(session_id=b)
        with sm() as db:
            waiting = db.execute(text("SELECT args->>'session_id' FROM procrastinate_jobs "
                                      "WHERE status = 'todo' ORDER BY id")).scalars().all()
        assert waiting == [a, b, b]
        worker.run_worker(pg_settings, concurrency=2, wait=False, install_signal_handlers=False)
        for sid in (a, b):
            row = get(sm, sid)
            assert row.status == "done" and row.worker_id.startswith("worker@")
            assert row.attempts == 1  # the duplicate job found nothing to claim
            assert n_strides(sm, sid) == 5
        with sm() as db:
            left = db.execute(text("SELECT count(*) FROM procrastinate_jobs WHERE status IN ('todo', 'doing')"))
            assert left.scalar() == 0
    finally:
        worker.close_api_apps()
        sm.kw["bind"].dispose()


def test_procrastinate_recovery_requeues_and_frees_dead_jobs(pg_settings: Settings,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import asyncio

    from sqlalchemy import text

    from server.processing import worker

    monkeypatch.setattr(jobs, "_default_processor", data_processor())
    sm = make_sessionmaker(make_engine(pg_settings.resolved_database_url))
    url = pg_settings.resolved_database_url
    try:
        stalled = make_session(sm, seed=1)
        orphan = make_session(sm, seed=2)  # queued, but the API died before deferring its job
        queue.enqueue(pg_settings, stalled)
        assert jobs.claim(sm, stalled, "dead-machine")
        with sm() as db:
            db.execute(update(Session).where(Session.id == stalled)
                       .values(heartbeat_at=datetime.now(UTC) - timedelta(hours=1)))
            # Its job is "doing" with no live worker: it would stay so forever unless someone ends it.
            db.execute(text("UPDATE procrastinate_jobs SET status = 'doing' WHERE queueing_lock = :s"),
                       {"s": stalled})
            db.commit()
        worker.close_api_apps()
        app = worker.make_app(url, pg_settings)

        async def recover() -> int:
            async with app.open_async():
                return await worker.recover_async(app, url, pg_settings)

        assert asyncio.run(recover()) == 2
        with sm() as db:
            waiting = set(db.execute(text("SELECT args->>'session_id' FROM procrastinate_jobs "
                                          "WHERE status = 'todo'")).scalars())
        assert waiting == {stalled, orphan}
        with sm() as db:
            old = db.execute(text("SELECT status FROM procrastinate_jobs WHERE queueing_lock = :s "
                                  "ORDER BY id LIMIT 1"), {"s": stalled}).scalar()
        assert old == "failed"
        worker.run_worker(pg_settings, wait=False, install_signal_handlers=False)
        assert get(sm, stalled).status == "done" and get(sm, orphan).status == "done"
    finally:
        sm.kw["bind"].dispose()


def _rows_naming(db, value: str) -> dict[str, int]:  # noqa: ANN001
    """Per table, the rows in which ``value`` appears in any column (every table of the database)."""
    from sqlalchemy import inspect, text

    found = {}
    for table in inspect(db.get_bind()).get_table_names():
        rows = db.execute(text(f'SELECT * FROM "{table}"')).all()
        hits = sum(1 for r in rows if value in repr(tuple(r)))
        if hits:
            found[table] = hits
    return found


def test_deleting_a_patient_leaves_no_row_naming_their_sessions(settings: Settings, sm) -> None:  # noqa: ANN001
    """Sessions, raw data, results and, on PostgreSQL, procrastinate's job rows (waiting, failed, running) of a
    deleted patient are gone or anonymised; another patient's job rows stay."""
    from sqlalchemy import text

    from server.patients import service as patients
    from server.processing import worker

    pg = settings.resolved_database_url.startswith("postgresql")
    gone, kept = make_session(sm, seed=1), make_session(sm, seed=2)
    jobs.run_queued(sm, processor=data_processor())
    assert n_strides(sm, gone) == 5
    if pg:
        url = settings.resolved_database_url
        worker.apply_schema(url)
        try:
            app = worker._api_app(url)
            for sid in (gone, gone, gone, kept):
                app.configure_task(worker.PROCESS_TASK).defer(session_id=sid)
        finally:
            worker.close_api_apps()
        with sm() as db:
            ids = db.execute(text("SELECT id FROM procrastinate_jobs WHERE args->>'session_id' = :s ORDER BY id"),
                             {"s": gone}).scalars().all()
            db.execute(text("UPDATE procrastinate_jobs SET status = 'failed' WHERE id = :i"), {"i": ids[0]})
            db.execute(text("UPDATE procrastinate_jobs SET status = 'doing' WHERE id = :i"), {"i": ids[1]})
            db.commit()
    with sm() as db:
        assert _rows_naming(db, gone)
        patient_id = db.get(Session, gone).patient_id
        patients.delete_patient(db, patient_id)
        db.commit()
    with sm() as db:
        assert _rows_naming(db, gone) == {}
        assert _rows_naming(db, patient_id) == {}
        assert db.get(Session, kept) is not None and n_strides(sm, kept) == 5
        if pg:
            statuses = db.execute(text("SELECT status, args->>'session_id' FROM procrastinate_jobs ORDER BY id")).all()
            assert sorted(tuple(r) for r in statuses) == [("doing", ""), ("todo", kept)]
