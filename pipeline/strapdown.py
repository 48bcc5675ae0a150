"""Strapdown integration of a gyroscope over short cycles: each sample's orientation in the frame of its cycle's
first sample, and the whole turn over each cycle.

The turn over the interval before a sample is taken at the interval's mean rate (a unit quaternion; over a gait
cycle a 1 deg/s bias turns the frame by less than a degree). The ordered products over every cycle at once come from a
segmented prefix scan: log2 of the longest cycle passes over the cycles' samples (qmt's ``quatFromGyrStrapdown`` one
sample at a time, here vectorised over many cycles).
"""

from __future__ import annotations

import numpy as np


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products (M, 4) of unit quaternions ``(w, x, y, z)`` (M, 4)."""
    aw, av, bw, bv = a[:, 0], a[:, 1:], b[:, 0], b[:, 1:]
    w = aw * bw - np.einsum("ij,ij->i", av, bv)
    return np.column_stack([w, aw[:, None] * bv + bw[:, None] * av + np.cross(av, bv)])


def cycle_frames(gyr_rps: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every sample of the cycles ``[starts[k], ends[k])`` its orientation in the frame of its cycle's first
    sample: ``(q, idx, owner)``, unit quaternions (M, 4) ``(w, x, y, z)`` turning a vector from the sample's frame
    into the first one's, the sample index (M,) into ``gyr_rps`` and the cycle it belongs to (M,). ``gyr_rps``
    (N, 3) on a uniform grid at ``fs_hz``, finite on the cycles; cycles may not overlap."""
    starts = np.asarray(starts, dtype=int)
    ends = np.asarray(ends, dtype=int)
    lengths = np.maximum(ends - starts, 0)
    owner = np.repeat(np.arange(starts.size), lengths)
    first = np.repeat(starts, lengths)
    idx = first + (np.arange(owner.size) - np.repeat(np.cumsum(lengths) - lengths, lengths))
    if owner.size == 0:
        return np.zeros((0, 4)), idx, owner
    # the turn over the interval before each sample (none before a cycle's first one)
    half = 0.25 * (gyr_rps[np.maximum(idx - 1, 0)] + gyr_rps[idx]) / fs_hz
    half[idx == first] = 0.0
    angle = np.sqrt(np.einsum("ij,ij->i", half, half))
    sinc = np.where(angle > 1e-12, np.sin(angle) / np.maximum(angle, 1e-12), 1.0)
    q = np.column_stack([np.cos(angle), half * sinc[:, None]])
    pos = idx - first  # samples since the cycle's first
    d = 1
    while d < int(lengths.max()):
        later = np.flatnonzero(pos >= d)
        q[later] = _qmul(q[later - d], q[later])
        d *= 2
    return q, idx, owner


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The vectors ``v`` (M, 3) turned by the unit quaternions ``q`` (M, 4)."""
    w, u = q[:, 0], q[:, 1:]
    uv = np.cross(u, v)
    return v + 2.0 * (w[:, None] * uv + np.cross(u, uv))


def cycle_turn_deg(gyr_rps: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Per cycle ``[starts[k], ends[k]]`` (the end sample included) the angle (K,) [deg] the sensor turned by from
    its first sample to its last, whatever the axis (:func:`cycle_frames`). Over a gait cycle, from one foot
    strike to the next, a segment returns to its posture relative to the body, so this is the body's turn: its
    change of heading."""
    starts = np.asarray(starts, dtype=int)
    ends = np.asarray(ends, dtype=int) + 1
    out = np.zeros(starts.size)
    q, _, owner = cycle_frames(gyr_rps, fs_hz, starts, ends)
    if owner.size == 0:
        return out
    last = np.flatnonzero(np.r_[owner[1:] != owner[:-1], True])
    out[owner[last]] = np.degrees(2.0 * np.arccos(np.clip(np.abs(q[last, 0]), 0.0, 1.0)))
    return out
