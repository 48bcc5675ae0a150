"""Test support: processed sessions with known strides, inserted straight into the database (tests, bench/trends.py).

This bypasses upload and the pipeline on purpose: trend statistics are checked against strides whose values are
known exactly. The rows are the same the job runner writes (Session status "done", Stride rows), and summaries come
from the production :func:`server.trends.summaries.refresh_session`.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

import numpy as np
from sqlalchemy import insert
from sqlalchemy.orm import Session as DbSession

from pipeline.types import RawSensorStream
from server.codec import content_sha256, encode_samples
from server.db import new_id
from server.results.models import Stride
from server.sessions.models import Batch, Session, SessionSensor
from server.trends.summaries import refresh_session
from server.utc import utcnow

DEFAULTS: dict[str, float] = {
    "duration_s": 1.1, "stance_pct": 60.0, "peak_swing_flexion_deg": 60.0, "min_flexion_deg": 2.0,
    "stance_flexion_deg": 15.0, "quality": 1.0,
}


def stride_rows(session_id: str, patient_id: str, started_at: datetime, leg: str, n: int,
                **columns: Any) -> list[dict[str, Any]]:
    """``n`` consecutive strides of one leg; any Stride column may be given as a scalar or a length-n array
    (``estimator`` and ``activity`` as a string or a list, ``fallback`` as a bool or a list). ``rom_deg`` defaults
    to peak - min, timing follows ``duration_s``."""
    labels = ("estimator", "activity", "fallback")
    cols = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)) for k, v in {**DEFAULTS, **{
        k: v for k, v in columns.items() if k not in labels}}.items()}
    estimators = _per_stride(columns.get("estimator", "go"), n)
    activities = _per_stride(columns.get("activity", "walking"), n)
    fallbacks = _per_stride(columns.get("fallback", False), n)
    dur = cols["duration_s"]
    t_start = np.concatenate([[0.0], np.cumsum(dur)[:-1]]) + 1.0
    rom = cols.get("rom_deg", cols["peak_swing_flexion_deg"] - cols["min_flexion_deg"])
    stance = dur * cols["stance_pct"] / 100.0
    return [{
        "session_id": session_id, "patient_id": patient_id, "leg": leg, "index": i,
        "started_at": started_at + timedelta(seconds=float(t_start[i])), "t_start_s": float(t_start[i]),
        "t_end_s": float(t_start[i] + dur[i]), "duration_s": float(dur[i]),
        "t_toe_off_s": float(t_start[i] + stance[i]), "stance_time_s": float(stance[i]),
        "swing_time_s": float(dur[i] - stance[i]), "stance_pct": float(cols["stance_pct"][i]),
        "peak_swing_flexion_deg": float(cols["peak_swing_flexion_deg"][i]),
        "min_flexion_deg": float(cols["min_flexion_deg"][i]), "rom_deg": float(rom[i]),
        "stance_flexion_deg": float(cols["stance_flexion_deg"][i]), "estimator": estimators[i],
        "activity": activities[i], "fallback": bool(fallbacks[i]), "quality": float(cols["quality"][i]),
        "quality_reasons": [],
    } for i in range(n)]


def _per_stride(value: Any, n: int) -> list[Any]:
    return [value] * n if isinstance(value, str | bool) else list(value)


def add_session(db: DbSession, patient_id: str, started_at: datetime, legs: dict[str, dict[str, Any]], *,
                status: str = "done", gaps: dict[str, int] | None = None, refresh: bool = True) -> str:
    """A processed session with strides per leg: ``legs = {"left": {"n": 30, "peak_swing_flexion_deg": ...}}``.
    Returns the session id. Flushes; the caller commits."""
    sid = new_id()
    summary = {"algorithm_version": "seed", "activity": "walking", "warnings": [], "legs": {
        leg: {"n_strides": int(spec["n"]), "gaps": int((gaps or {}).get(leg, 0))} for leg, spec in legs.items()}}
    db.execute(insert(Session).values(
        id=sid, patient_id=patient_id, client_session_id=sid, started_at=started_at, activity="walking",
        status=status, algorithm_version="seed", summary=summary, created_at=utcnow(), completed_at=utcnow(),
        processed_at=utcnow(), attempts=1))
    rows = [r for leg, spec in legs.items()
            for r in stride_rows(sid, patient_id, started_at, leg, int(spec["n"]),
                                 **{k: v for k, v in spec.items() if k != "n"})]
    if rows:
        db.execute(insert(Stride), rows)
    if refresh:
        refresh_session(db, sid)
    return sid


def add_stream_batches(db: DbSession, session_id: str, streams: list[RawSensorStream], n_batches: int) -> None:
    """Declare each stream's sensor on the session and store its samples as ``n_batches`` raw batches, exactly as
    the upload path stores them (so the job runner processes them like uploaded data)."""
    for s in streams:
        db.add(SessionSensor(session_id=session_id, sensor_id=s.sensor_id, leg=s.leg, segment=s.segment,
                             sample_rate_hz=s.fs_hz, gyro_unit=s.gyro_unit, acc_unit=s.acc_unit))
        for seq, part in enumerate(np.array_split(np.arange(len(s.t_s)), n_batches)):
            t_ms, g, a = s.t_s[part] * 1000.0, s.gyr[part], s.acc[part]
            tb, gb, ab = encode_samples(t_ms, g, a)
            db.add(Batch(session_id=session_id, sensor_id=s.sensor_id, seq=seq, t0_ms=float(t_ms[0]),
                         n_samples=len(part), t_first_ms=float(t_ms[0]), t_last_ms=float(t_ms[-1]),
                         content_sha256=content_sha256(t_ms, g, a), t_ms=tb, gyro=gb, acc=ab))
