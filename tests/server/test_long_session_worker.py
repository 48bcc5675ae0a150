"""A session longer than one processing chunk goes through the worker's default processor window by window
(server.sessions.rawdata.StoredStreams, pipeline.long_sessions): never decoded whole, results as the pipeline's."""

from __future__ import annotations

import numpy as np
import pytest
from sqlalchemy import select

from pipeline.long_sessions import ArraySource, process_source
from pipeline.params import LongSessionParams
from pipeline.simulate import SimConfig, simulate_session
from pipeline.types import RawSensorStream
from server.patients.models import Patient
from server.processing import jobs
from server.results.models import KneeAngleTrace, Stride
from server.sessions import rawdata
from server.sessions.models import Session
from tests.server.test_jobs import STARTED_AT, get, sm  # noqa: F401 - the sm fixture
from tests.support.seed import add_stream_batches

CHUNKING = LongSessionParams(chunk_s=240.0, overlap_s=20.0, full_rate_trace_s=0.0)


@pytest.fixture(scope="module")
def streams() -> list[RawSensorStream]:
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=11, duration_s=720.0,
                                     activities=("standing",), bout_strides=40))
    return sim.streams


def _queued_session(sm, streams: list[RawSensorStream]) -> str:  # noqa: ANN001, F811
    with sm() as db:
        patient = Patient(display_name="long")
        db.add(patient)
        db.flush()
        sess = Session(patient_id=patient.id, client_session_id="long-1", started_at=STARTED_AT,
                       activity="walking", status="queued")
        db.add(sess)
        db.flush()
        add_stream_batches(db, sess.id, streams, n_batches=72)  # 10 s batches
        db.commit()
        return sess.id


def test_long_session_is_processed_window_by_window(sm, streams, monkeypatch) -> None:  # noqa: ANN001, F811
    sid = _queued_session(sm, streams)
    with sm() as db:
        stored = rawdata.load_streams(db, sid)  # the samples as stored (float32), for the expected result
    expected = process_source(ArraySource(stored), chunking=CHUNKING)

    asked: list[tuple[float, float]] = []
    window = rawdata.StoredStreams.window

    def spy(self, t0_s: float, t1_s: float) -> list[RawSensorStream]:  # noqa: ANN001
        asked.append((t0_s, t1_s))
        return window(self, t0_s, t1_s)

    def whole(*_a, **_k) -> None:  # noqa: ANN002, ANN003
        raise AssertionError("a long session must not be decoded whole")

    monkeypatch.setattr(rawdata, "CHUNKING", CHUNKING)
    monkeypatch.setattr(rawdata.StoredStreams, "window", spy)
    monkeypatch.setattr(rawdata, "load_streams", whole)
    assert jobs.run_queued(sm) == 1

    sess = get(sm, sid)
    assert sess.status == "done", sess.error
    assert len(asked) == 3
    assert max(b - a for a, b in asked) <= CHUNKING.chunk_s + 2 * CHUNKING.overlap_s + 1e-6
    with sm() as db:
        rows = db.scalars(select(Stride).where(Stride.session_id == sid).order_by(Stride.leg, Stride.index)).all()
        traces = {t.leg: t for t in db.scalars(select(KneeAngleTrace).where(KneeAngleTrace.session_id == sid))}
    for leg in ("left", "right"):
        mine = [r for r in rows if r.leg == leg]
        exp = expected.legs[leg].strides
        assert len(mine) == len(exp) > 500
        assert np.allclose([r.t_start_s for r in mine], [s.t_start_s for s in exp])
        assert np.allclose([r.peak_swing_flexion_deg for r in mine], [s.peak_swing_flexion_deg for s in exp],
                           atol=1e-4)
        assert traces[leg].fs_hz == pytest.approx(25.0)
        assert traces[leg].n == expected.legs[leg].t_s.size
    assert sess.summary["legs"]["left"]["n_strides"] == len(expected.legs["left"].strides)


def test_short_session_is_decoded_whole(sm, streams, monkeypatch) -> None:  # noqa: ANN001, F811
    """At most one chunk long: the streams are loaded at once and processed as one block, as before."""
    sid = _queued_session(sm, [s for s in streams])
    monkeypatch.setattr(rawdata, "CHUNKING", LongSessionParams(chunk_s=800.0, overlap_s=20.0))
    with sm() as db:
        got = rawdata.load_input(sm, db, sid)
    assert isinstance(got, list) and len(got) == 4
    monkeypatch.setattr(rawdata, "CHUNKING", CHUNKING)
    with sm() as db:
        got = rawdata.load_input(sm, db, sid)
    assert isinstance(got, rawdata.StoredStreams)
    assert rawdata.input_counts(got) == (4, sum(len(s.t_s) for s in streams),
                                         ["left", "left", "right", "right"])
