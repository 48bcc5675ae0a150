"""Binary storage of uploaded IMU samples and their reassembly into pipeline streams.

A :class:`server.models.Batch` holds ``t_ms`` as little-endian float64 (N,) and ``gyro``/``acc`` as little-endian
float32 (N, 3) row-major, in the units the session declared for the sensor. float32 keeps 7 significant digits,
far below IMU noise, and halves the storage; time stays float64 because ms since session start over hours would
lose sub-ms resolution in float32.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

from pipeline.types import RawSensorStream
from server.models import Batch, SessionSensor

T_DTYPE = np.dtype("<f8")
XYZ_DTYPE = np.dtype("<f4")


def encode_samples(t_ms: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> tuple[bytes, bytes, bytes]:
    """Encode one batch: ``t_ms`` float64 (N,), ``gyro``/``acc`` float32 (N, 3), little-endian bytes."""
    t = np.ascontiguousarray(np.asarray(t_ms, dtype=np.float64).reshape(-1), dtype=T_DTYPE)
    g = np.ascontiguousarray(np.asarray(gyro, dtype=np.float64).reshape(-1, 3), dtype=XYZ_DTYPE)
    a = np.ascontiguousarray(np.asarray(acc, dtype=np.float64).reshape(-1, 3), dtype=XYZ_DTYPE)
    if not (len(t) == len(g) == len(a)):
        raise ValueError(f"length mismatch: t {len(t)}, gyro {len(g)}, acc {len(a)}")
    return t.tobytes(), g.tobytes(), a.tobytes()


def decode_samples(t_ms: bytes, gyro: bytes, acc: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_samples`: float64 arrays ``t_ms`` (N,), ``gyro`` (N, 3), ``acc`` (N, 3)."""
    t = np.frombuffer(t_ms, dtype=T_DTYPE).astype(np.float64)
    g = np.frombuffer(gyro, dtype=XYZ_DTYPE).astype(np.float64).reshape(-1, 3)
    a = np.frombuffer(acc, dtype=XYZ_DTYPE).astype(np.float64).reshape(-1, 3)
    return t, g, a


def content_sha256(t_ms: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> str:
    """SHA-256 of the canonical binary form of a batch's parsed values.

    Hashing float64 values (not the JSON text) makes whitespace, number formatting ("1" vs "1.0") and gzip
    irrelevant, while any real change of a value gives a different hash (idempotent replay -> 200, else 409).
    """
    h = hashlib.sha256()
    for arr in (np.asarray(t_ms, dtype=np.float64).reshape(-1),
                np.asarray(gyro, dtype=np.float64).reshape(-1),
                np.asarray(acc, dtype=np.float64).reshape(-1)):
        data = np.ascontiguousarray(arr, dtype=T_DTYPE)
        h.update(len(data).to_bytes(8, "little"))
        h.update(data.tobytes())
    return h.hexdigest()


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
            leg=sensor.leg,  # type: ignore[arg-type]
            segment=sensor.segment,  # type: ignore[arg-type]
            fs_hz=float(sensor.sample_rate_hz),
            t_s=t_ms / 1000.0,
            gyr=gyro,
            acc=acc,
            gyro_unit=sensor.gyro_unit,  # type: ignore[arg-type]
            acc_unit=sensor.acc_unit,  # type: ignore[arg-type]
        ))
    return out
