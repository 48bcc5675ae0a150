"""Binary form of the continuous knee angle stored in :class:`server.models.KneeAngleTrace`.

The pipeline returns a leg's angle on its own time grid (uniform at ``fs_hz`` apart from gaps, which it may leave
out or fill with NaN). Storing it on a strictly uniform grid means only ``t0_s`` and ``fs_hz`` describe time, so
the arrays are ``angle_deg`` float32 and ``estimator_codes`` uint8, little-endian; samples the grid has but the
pipeline did not produce are NaN with code 0 (estimator ``""``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ANGLE_DTYPE = np.dtype("<f4")
CODE_DTYPE = np.dtype("u1")


@dataclass(frozen=True)
class EncodedTrace:
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
