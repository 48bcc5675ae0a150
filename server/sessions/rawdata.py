"""Reassembly of a session's stored batches into pipeline streams (the encoding is :mod:`server.codec`): all at once
(:func:`load_streams`), or, for a session longer than one processing chunk, window by window
(:class:`StoredStreams`, a :class:`pipeline.long_sessions.StreamSource`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from pipeline.params import WALKING, LongSessionParams
from pipeline.types import AccUnit as PipelineAccUnit
from pipeline.types import GyroUnit as PipelineGyroUnit
from pipeline.types import Leg as PipelineLeg
from pipeline.types import RawSensorStream
from pipeline.types import Segment as PipelineSegment
from server.codec import decode_samples
from server.enums import AccUnit, GyroUnit, Leg, Segment
from server.sessions.models import Batch, SessionSensor


def concat_batches(batches: Iterable[Batch], sample_rate_hz: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode and join batches, sorted by time; a repeated timestamp keeps the sample of the lowest seq.

    With ``sample_rate_hz``, samples closer than a quarter period to the previous one are dropped too: the same
    sample re-sent under another seq with a slightly different stamp (overlapping batches) must not count twice.
    """
    parts = [decode_samples(b.t_ms, b.gyro, b.acc) for b in sorted(batches, key=lambda b: b.seq)]
    if not parts:
        return np.empty(0), np.empty((0, 3)), np.empty((0, 3))
    t = np.concatenate([p[0] for p in parts])
    g = np.concatenate([p[1] for p in parts])
    a = np.concatenate([p[2] for p in parts])
    # Stable sort keeps seq order among equal timestamps, so np.unique's first index is the lowest seq.
    order = np.argsort(t, kind="stable")
    t, g, a = t[order], g[order], a[order]
    _, first = np.unique(t, return_index=True)
    t, g, a = t[first], g[first], a[first]
    if sample_rate_hz and t.size > 1:
        keep = np.concatenate(([True], np.diff(t) >= 250.0 / sample_rate_hz))
        t, g, a = t[keep], g[keep], a[keep]
    return t, g, a


# The chunking the worker processes long sessions with (pipeline.params.LongSessionParams); tests shorten it.
CHUNKING: LongSessionParams = WALKING.long_sessions

# Batches starting this long [ms] before a window are read too: a sample re-sent in an earlier batch under another
# seq must meet its copy to be dropped as a duplicate (concat_batches), whatever window it falls in.
_WINDOW_MARGIN_MS = 1000.0


def _sensors(db: DbSession, session_id: str) -> list[SessionSensor]:
    return list(db.scalars(
        select(SessionSensor).where(SessionSensor.session_id == session_id).order_by(SessionSensor.sensor_id)
    ).all())


def _stream(sensor: SessionSensor, batches: Iterable[Batch], t0_ms: float = -np.inf,
            t1_ms: float = np.inf) -> RawSensorStream | None:
    t_ms, gyro, acc = concat_batches(batches, sensor.sample_rate_hz)
    if np.isfinite(t0_ms) or np.isfinite(t1_ms):
        keep = (t_ms >= t0_ms) & (t_ms < t1_ms)
        t_ms, gyro, acc = t_ms[keep], gyro[keep], acc[keep]
    if t_ms.size == 0:
        return None
    return RawSensorStream(
            sensor_id=sensor.sensor_id,
            # The stored strings were validated against these vocabularies when the session was created.
            leg=cast(PipelineLeg, Leg(sensor.leg).value),
            segment=cast(PipelineSegment, Segment(sensor.segment).value),
            fs_hz=float(sensor.sample_rate_hz),
            t_s=t_ms / 1000.0,
            gyr=gyro,
            acc=acc,
            gyro_unit=cast(PipelineGyroUnit, GyroUnit(sensor.gyro_unit).value),
            acc_unit=cast(PipelineAccUnit, AccUnit(sensor.acc_unit).value),
        )


def load_streams(db: DbSession, session_id: str) -> list[RawSensorStream]:
    """Every sensor of a session as one :class:`RawSensorStream` (t in seconds, declared units).

    Sensors without any batch are left out: the pipeline decides what a missing segment means.
    """
    out: list[RawSensorStream] = []
    for sensor in _sensors(db, session_id):
        batches = db.scalars(
            select(Batch).where(Batch.session_id == session_id, Batch.sensor_id == sensor.sensor_id)
        ).all()
        stream = _stream(sensor, batches) if batches else None
        if stream is not None:
            out.append(stream)
    return out


class StoredStreams:
    """A session's stored batches as a :class:`pipeline.long_sessions.StreamSource`: each window decodes only the
    batches that overlap it (``t_first_ms``/``t_last_ms``), in a short database session of its own, so a day-long
    session is never decoded whole. ``chunking`` is what the worker processes it with."""

    def __init__(self, sm: sessionmaker[DbSession], session_id: str, span_ms: tuple[float, float],
                 sensors: list[SessionSensor], n_samples: int, chunking: LongSessionParams) -> None:
        self.sm, self.session_id, self.span_ms = sm, session_id, span_ms
        self.sensors, self.n_samples, self.chunking = sensors, n_samples, chunking

    def span_s(self) -> tuple[float, float]:
        """First and last stored sample time [s] over all sensors."""
        return self.span_ms[0] / 1000.0, self.span_ms[1] / 1000.0

    def window(self, t0_s: float, t1_s: float) -> list[RawSensorStream]:
        """Every sensor's samples with ``t0_s <= t < t1_s``; sensors without any are left out."""
        # open ends become the stored span (a database compares finite numbers)
        t0_ms = max(1000.0 * t0_s, self.span_ms[0] - _WINDOW_MARGIN_MS)
        t1_ms = min(1000.0 * t1_s, self.span_ms[1] + _WINDOW_MARGIN_MS)
        out = []
        with self.sm() as db:
            for sensor in self.sensors:
                batches = db.scalars(select(Batch).where(
                    Batch.session_id == self.session_id, Batch.sensor_id == sensor.sensor_id,
                    Batch.t_last_ms >= t0_ms - _WINDOW_MARGIN_MS, Batch.t_first_ms < t1_ms)).all()
                stream = _stream(sensor, batches, t0_ms, t1_ms) if batches else None
                if stream is not None:
                    out.append(stream)
        return out


def load_input(sm: sessionmaker[DbSession], db: DbSession, session_id: str
               ) -> list[RawSensorStream] | StoredStreams:
    """What the worker processes: every stream decoded (:func:`load_streams`) when the stored samples span at most
    one chunk (:data:`CHUNKING`), else a :class:`StoredStreams` read window by window while processing."""
    first, last, n = db.execute(select(func.min(Batch.t_first_ms), func.max(Batch.t_last_ms),
                                       func.sum(Batch.n_samples)).where(Batch.session_id == session_id)).one()
    if first is None or (last - first) / 1000.0 <= CHUNKING.chunk_s:
        return load_streams(db, session_id)
    sensors = _sensors(db, session_id)
    for sensor in sensors:
        db.expunge(sensor)  # read again in the windows' own database sessions
    return StoredStreams(sm, session_id, (float(first), float(last)), sensors, int(n), CHUNKING)


def input_counts(data: list[RawSensorStream] | StoredStreams) -> tuple[int, int, list[str]]:
    """Sensors, samples and the legs of the sensors of what :func:`load_input` returned (for logs and the
    summary)."""
    if isinstance(data, StoredStreams):
        return len(data.sensors), data.n_samples, [s.leg for s in data.sensors]
    return len(data), sum(len(s.t_s) for s in data), [s.leg for s in data]
