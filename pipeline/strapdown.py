"""Strapdown integration of a gyroscope over short cycles: each sample's orientation in the frame of its cycle's
first sample, and the whole turn over each cycle.

The turn over the interval before a sample is taken at the interval's mean rate (a unit quaternion; over a gait
cycle a 1 deg/s bias turns the frame by less than a degree), and the turns are chained sample by sample as in qmt's
``quatFromGyrStrapdown``, here for many cycles side by side.
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
    into the first one's, the sample index (M,) into ``gyr_rps`` and the cycle it belongs to (M,), cycle by cycle
    in order. ``gyr_rps`` (N, 3) on a uniform grid at ``fs_hz``, finite on the cycles.

    All cycles are integrated side by side, one step per sample of the longest (shorter ones padded with no turn):
    as many numpy passes as the longest cycle has samples, each over the K cycles, so the work is the samples'
    and the Python overhead that of one cycle."""
    starts = np.asarray(starts, dtype=int)
    ends = np.asarray(ends, dtype=int)
    lengths = np.maximum(ends - starts, 0)
    owner = np.repeat(np.arange(starts.size), lengths)
    first = np.repeat(starts, lengths)
    pos = np.arange(owner.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)  # samples since the first
    idx = first + pos
    if owner.size == 0:
        return np.zeros((0, 4)), idx, owner
    # the turn over the interval before each sample (none before a cycle's first one), on a (K, L) padded grid
    half = np.zeros((starts.size, int(lengths.max()), 3))
    later = pos > 0
    half[owner[later], pos[later]] = 0.25 * (gyr_rps[idx[later] - 1] + gyr_rps[idx[later]]) / fs_hz
    angle = np.sqrt(np.einsum("kli,kli->kl", half, half))
    sinc = np.where(angle > 1e-12, np.sin(angle) / np.maximum(angle, 1e-12), 1.0)
    step = np.concatenate([np.cos(angle)[..., None], half * sinc[..., None]], axis=-1)
    frames = np.empty_like(step)
    frames[:, 0] = step[:, 0]
    for j in range(1, step.shape[1]):
        frames[:, j] = _qmul(frames[:, j - 1], step[:, j])
    return frames[owner, pos], idx, owner


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
