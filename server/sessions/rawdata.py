"""Reassembly of a session's stored batches into pipeline streams (the encoding is :mod:`server.codec`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

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


def load_streams(db: DbSession, session_id: str) -> list[RawSensorStream]:
    """Every sensor of a session as one :class:`RawSensorStream` (t in seconds, declared units).

    Sensors without any batch are left out: the pipeline decides what a missing segment means.
    """
    sensors = db.scalars(
        select(SessionSensor).where(SessionSensor.session_id == session_id).order_by(SessionSensor.sensor_id)
    ).all()
    out: list[RawSensorStream] = []
    for sensor in sensors:
        batches = db.scalars(
            select(Batch).where(Batch.session_id == session_id, Batch.sensor_id == sensor.sensor_id)
        ).all()
        if not batches:
            continue
        t_ms, gyro, acc = concat_batches(batches, sensor.sample_rate_hz)
        out.append(RawSensorStream(
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
        ))
    return out
