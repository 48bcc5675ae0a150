"""server.codec and server.sessions.rawdata: binary round trip and reassembly of batches into pipeline streams."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from server.codec import content_sha256, decode_samples, encode_samples
from server.db import make_engine, make_sessionmaker
from server.patients.models import Patient
from server.sessions.models import Batch, Session, SessionSensor
from server.sessions.rawdata import load_streams


def test_encode_decode_round_trip_keeps_time_exact_and_xyz_to_float32() -> None:
    rng = np.random.default_rng(1)
    t = 3_600_000.0 + np.arange(50) * 10.0 + 0.125
    g = rng.normal(0, 200, (50, 3))
    a = rng.normal(0, 9.81, (50, 3))
    tb, gb, ab = encode_samples(t, g, a)
    assert len(tb) == 50 * 8 and len(gb) == 50 * 12 and len(ab) == 50 * 12
    t2, g2, a2 = decode_samples(tb, gb, ab)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_allclose(g2, g, rtol=1e-6)
    np.testing.assert_allclose(a2, a, rtol=1e-6)


def test_content_hash_depends_on_values_only() -> None:
    t = np.array([0.0, 10.0])
    g = np.array([[1, 2, 3], [4, 5, 6]])
    a = np.zeros((2, 3))
    assert content_sha256(t, g, a) == content_sha256(t.tolist(), g.astype(float), a)
    assert content_sha256(t, g, a) != content_sha256(t, g + 1e-9, a)
    # Same flat values, different split between the arrays: must differ.
    assert content_sha256(t, g, a) != content_sha256(np.array([0.0]), g, a)


def test_load_streams_sorts_and_drops_duplicate_timestamps(database_url: str) -> None:
    engine = make_engine(database_url)
    sm = make_sessionmaker(engine)
    fs = 100.0
    with sm() as db:
        patient = Patient()
        db.add(patient)
        db.flush()
        sess = Session(patient_id=patient.id, client_session_id="c1", started_at=datetime.now(UTC))
        sess.sensors = [
            SessionSensor(sensor_id="L-shank", leg="left", segment="shank", sample_rate_hz=fs,
                          gyro_unit="rad/s", acc_unit="g"),
            SessionSensor(sensor_id="L-thigh", leg="left", segment="thigh", sample_rate_hz=fs,
                          gyro_unit="deg/s", acc_unit="m/s2"),
        ]
        db.add(sess)
        db.flush()
        t_all = np.arange(300) * 10.0
        gyro = np.stack([t_all, -t_all, t_all * 2], axis=1) / 1000.0
        acc = np.ones((300, 3))
        # Three batches stored out of order; the third overlaps the second by 20 samples.
        for seq, sl in [(2, slice(180, 300)), (0, slice(0, 100)), (1, slice(100, 200))]:
            tb, gb, ab = encode_samples(t_all[sl], gyro[sl], acc[sl])
            db.add(Batch(session_id=sess.id, sensor_id="L-shank", seq=seq, t0_ms=float(t_all[sl][0]),
                         n_samples=len(t_all[sl]), t_first_ms=float(t_all[sl][0]), t_last_ms=float(t_all[sl][-1]),
                         content_sha256="x", t_ms=tb, gyro=gb, acc=ab))
        db.commit()
        streams = load_streams(db, sess.id)
    engine.dispose()
    assert [s.sensor_id for s in streams] == ["L-shank"]  # the thigh has no batch
    s = streams[0]
    assert (s.leg, s.segment, s.fs_hz, s.gyro_unit, s.acc_unit) == ("left", "shank", fs, "rad/s", "g")
    assert s.t_s.shape == (300,) and s.gyr.shape == (300, 3) and s.acc.shape == (300, 3)
    np.testing.assert_allclose(s.t_s, t_all / 1000.0)
    assert np.all(np.diff(s.t_s) > 0)
    np.testing.assert_allclose(s.gyr, gyro, rtol=1e-6)
