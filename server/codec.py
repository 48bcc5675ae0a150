"""The binary encodings the service stores: raw IMU batches and continuous knee-angle traces.

Batches (:class:`server.sessions.models.Batch`): ``t_ms`` little-endian float64 (N,), ``gyro``/``acc``
little-endian float32 (N, 3) row-major, in the units the session declared for the sensor. float32 keeps 7
significant digits, far below IMU noise, and halves the storage; time stays float64 because ms since session start
over hours would lose sub-ms resolution in float32.

Traces (:class:`server.results.models.KneeAngleTrace`): the pipeline returns a leg's angle on its own time grid
(uniform at ``fs_hz`` apart from gaps, which it may leave out or fill with NaN). Storing it on a strictly uniform
grid means only ``t0_s`` and ``fs_hz`` describe time, so the arrays are ``angle_deg`` float32 and
``estimator_codes`` uint8, little-endian; samples the grid has but the pipeline did not produce are NaN with code 0
(estimator ``""``).

Trend values (:class:`server.trends.models.TrendMetricValues`): the included values of one metric of one session,
leg and activity, little-endian float32, ascending.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

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


ANGLE_DTYPE = np.dtype("<f4")
CODE_DTYPE = np.dtype("u1")


@dataclass(frozen=True)
class EncodedTrace:
    """One leg's knee angle on a uniform grid, as stored."""

    t0_s: float
    fs_hz: float
    n: int
    angle_deg: bytes
    estimator_codes: bytes
    estimator_names: list[str]


def encode_trace(t_s: np.ndarray, angle_deg: np.ndarray, estimator: np.ndarray, fs_hz: float) -> EncodedTrace:
    """Place samples at ``t_s`` onto the uniform grid ``t0 + i / fs_hz``; ``estimator_names[0]`` is always ``""``."""
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    angle = np.asarray(angle_deg, dtype=np.float64).reshape(-1)
    est = np.asarray(estimator).astype(str).reshape(-1)
    if not (len(t) == len(angle) == len(est)):
        raise ValueError(f"trace length mismatch: t {len(t)}, angle {len(angle)}, estimator {len(est)}")
    if fs_hz <= 0 or not np.isfinite(fs_hz):
        raise ValueError(f"trace sample rate must be positive, got {fs_hz}")
    names = [""] + sorted(set(est.tolist()) - {""})
    if len(names) > 256:
        raise ValueError("more than 255 estimator names in one trace")
    if len(t) == 0:
        return EncodedTrace(0.0, float(fs_hz), 0, b"", b"", names)
    t0 = float(t[0])
    idx = np.rint((t - t0) * fs_hz).astype(np.int64)
    if np.any(np.diff(idx) <= 0):
        raise ValueError("trace time grid is not strictly increasing at the declared sample rate")
    n = int(idx[-1]) + 1
    out_angle = np.full(n, np.nan, dtype=ANGLE_DTYPE)
    out_angle[idx] = angle
    lookup = {name: code for code, name in enumerate(names)}
    out_codes = np.zeros(n, dtype=CODE_DTYPE)
    out_codes[idx] = np.fromiter((lookup[e] for e in est), dtype=CODE_DTYPE, count=len(est))
    out_codes[np.isnan(out_angle)] = 0
    return EncodedTrace(t0, float(fs_hz), n, out_angle.tobytes(), out_codes.tobytes(), names)


def decode_trace(t0_s: float, fs_hz: float, n: int, angle_deg: bytes, estimator_codes: bytes,
                 estimator_names: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_trace`: ``(t_s, angle_deg, estimator)`` with float64 times and angles."""
    angle = np.frombuffer(angle_deg, dtype=ANGLE_DTYPE).astype(np.float64)
    codes = np.frombuffer(estimator_codes, dtype=CODE_DTYPE)
    if len(angle) != n or len(codes) != n:
        raise ValueError(f"stored trace is corrupt: n={n}, {len(angle)} angles, {len(codes)} codes")
    t = t0_s + np.arange(n, dtype=np.float64) / fs_hz
    est = np.asarray(estimator_names, dtype=object)[codes] if n else np.empty(0, dtype=object)
    return t, angle, est.astype(str)


VALUE_DTYPE = np.dtype("<f4")


def encode_values(values: np.ndarray) -> bytes:
    """A trend summary's value array as stored (float32 keeps far more digits than the measurement has)."""
    return np.ascontiguousarray(values, dtype=VALUE_DTYPE).tobytes()


def decode_values(blob: bytes) -> np.ndarray:
    """Inverse of :func:`encode_values`."""
    return np.frombuffer(blob, dtype=VALUE_DTYPE)
