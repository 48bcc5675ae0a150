"""Strapdown integration of a gyroscope over short cycles: each sample's orientation in the frame of its cycle's
first sample, and the whole turn over each cycle.

The turn over the interval before a sample is taken at the interval's mean rate (a unit quaternion; over a gait
cycle a 1 deg/s bias turns the frame by less than a degree), and the turns are chained sample by sample as in qmt's
``quatFromGyrStrapdown``, here for many cycles side by side: one step per sample of the longest cycle (shorter ones
padded with no turn), each over the K cycles, so the work is the samples' and the Python overhead that of one cycle.
Quaternions are ``(w, x, y, z)``; on the padded grid each component is its own (L, K) array, so that every step
works on contiguous rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BLOCK_CELLS = 1 << 18
"""Samples of one padded grid (cycles times the longest of them) integrated at once: ~2 MB per array, some twenty
arrays; a 30-minute chunk at 200 Hz (~1800 strides of ~250 samples) in two groups."""


@dataclass(frozen=True)
class CycleFrames:
    """The orientations of :func:`chained_frames` on a padded grid.

    ``q``: (4, L, K) components of the unit quaternion turning a vector from the frame of sample ``l`` of cycle
    ``k`` into the frame of its first sample (past a cycle's end its last frame, held); ``lengths``: (K,) samples
    per cycle; ``pos``, ``owner``, ``idx``: (M,) for every sample of the cycles, in order, its place in its cycle,
    its cycle and its index into the input arrays."""

    q: np.ndarray
    lengths: np.ndarray
    pos: np.ndarray
    owner: np.ndarray
    idx: np.ndarray

    def padded(self, x: np.ndarray) -> np.ndarray:
        """(3, L, K) of the rows of ``x`` (N, 3) at the cycles' samples, zeros on the padding."""
        out = np.zeros((3, *self.q.shape[1:]))
        out[:, self.pos, self.owner] = x[self.idx].T
        return out


def chained_frames(gyr_rps: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray) -> CycleFrames:
    """Each sample's orientation in the frame of its cycle's first sample, for the cycles ``[starts[k], ends[k])``
    (module docstring). ``gyr_rps`` (N, 3) on a uniform grid at ``fs_hz``, finite on the cycles."""
    starts = np.asarray(starts, dtype=int)
    ends = np.asarray(ends, dtype=int)
    lengths = np.maximum(ends - starts, 0)
    owner = np.repeat(np.arange(starts.size), lengths)
    pos = np.arange(owner.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)  # samples since the first
    idx = np.repeat(starts, lengths) + pos
    steps = int(lengths.max()) if lengths.size else 0
    # the turn over the interval before each sample (none before a cycle's first one)
    half = np.zeros((3, steps, starts.size))
    later = pos > 0
    half[:, pos[later], owner[later]] = (0.25 * (gyr_rps[idx[later] - 1] + gyr_rps[idx[later]]) / fs_hz).T
    angle = np.sqrt(half[0] ** 2 + half[1] ** 2 + half[2] ** 2)
    sinc = np.where(angle > 1e-12, np.sin(angle) / np.maximum(angle, 1e-12), 1.0)
    step = np.stack([np.cos(angle), half[0] * sinc, half[1] * sinc, half[2] * sinc])
    q = np.empty_like(step)
    if steps:
        q[:, 0] = step[:, 0]
    w, x, y, z = q
    sw, sx, sy, sz = step
    for j in range(1, steps):  # the frame so far, then the step (Hamilton product)
        aw, ax, ay, az, bw, bx, by, bz = w[j - 1], x[j - 1], y[j - 1], z[j - 1], sw[j], sx[j], sy[j], sz[j]
        w[j] = aw * bw - ax * bx - ay * by - az * bz
        x[j] = aw * bx + ax * bw + ay * bz - az * by
        y[j] = aw * by - ax * bz + ay * bw + az * bx
        z[j] = aw * bz + ax * by - ay * bx + az * bw
    return CycleFrames(q=q, lengths=lengths, pos=pos, owner=owner, idx=idx)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The vectors ``v`` (M, 3) turned by the unit quaternions ``q`` (M, 4) (:func:`rotate_padded` row-wise)."""
    return rotate_padded(q.T, v.T).T


def rotate_padded(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The vectors ``v`` (3, ...) turned by the unit quaternions ``q`` (4, ...), components first (the padded grid's
    (3, L, K) and (4, L, K) arrays, or (3, M) and (4, M))."""
    w, ux, uy, uz = q
    vx, vy, vz = v
    cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx  # u x v
    return np.stack([vx + 2.0 * (w * cx + uy * cz - uz * cy),
                     vy + 2.0 * (w * cy + uz * cx - ux * cz),
                     vz + 2.0 * (w * cz + ux * cy - uy * cx)])


def cycle_blocks(starts: np.ndarray, ends: np.ndarray, max_cells: int = BLOCK_CELLS) -> list[np.ndarray]:
    """The indices of the cycles ``[starts[k], ends[k])`` in groups to integrate together, shortest cycles first:
    each group's padded grid (its cycle count times its longest cycle) holds at most ``max_cells`` samples, or one
    cycle. Grouping by length keeps the padding small, and the cap keeps the memory of the frames bounded whatever
    the number of cycles and however long the longest one is."""
    lengths = np.maximum(np.asarray(ends, dtype=int) - np.asarray(starts, dtype=int), 0)
    order = np.argsort(lengths, kind="stable")
    groups: list[np.ndarray] = []
    i = 0
    while i < order.size:
        span = np.arange(1, order.size - i + 1) * lengths[order[i:]]  # cells if the group ended at each cycle
        j = i + max(int(np.searchsorted(span, max_cells, side="right")), 1)
        groups.append(order[i:j])
        i = j
    return groups


def cycle_turn_deg(gyr_rps: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Per cycle ``[starts[k], ends[k]]`` (the end sample included) the angle (K,) [deg] the sensor turned by from
    its first sample to its last, whatever the axis (:func:`chained_frames`). Over a gait cycle, from one foot
    strike to the next, a segment returns to its posture relative to the body, so this is the body's turn: its
    change of heading."""
    starts = np.asarray(starts, dtype=int)
    ends = np.asarray(ends, dtype=int) + 1
    out = np.zeros(starts.size)
    for group in cycle_blocks(starts, ends):
        f = chained_frames(gyr_rps, fs_hz, starts[group], ends[group])
        some = f.lengths > 0
        w_last = f.q[0, f.lengths[some] - 1, np.flatnonzero(some)]
        out[group[some]] = np.degrees(2.0 * np.arccos(np.clip(np.abs(w_last), 0.0, 1.0)))
    return out
