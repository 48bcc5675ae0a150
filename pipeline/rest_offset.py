"""A sensor's constant accelerometer offset and gyro bias, as far as the session's own rests show them.

Uncalibrated MEMS accelerometers read up to 20-80 mg off per axis, with gain errors of 1-3 % (their data sheets):
up to ~1 m/s^2 at rest. That is the size of the quiet test's force tolerance (``PostureParams.force_tol``), so
the offset alone can make a sensor that never moves fail it, and the offset enters everything the accelerometer
feeds: the joint-centre fit (Seel et al. 2014, Eq. 5: the centres absorb it, centimetres off), the lever-arm
correction and the accelerometer knee angle (Eq. 6-7), and with them the absolute level of every stride.

At rest a sensor reads gravity plus its offset b, ``|a - b| = g``: the sphere constraint of multi-position
calibration (Skog & Händel 2006; Frosio, Pedersini & Borghese 2009), with the session's rests as the positions. A
single posture (quiet standing) fixes the part of b along gravity, which is the part the force test sees; rests in
other orientations (sitting puts the thigh horizontal) fix more. What the rests do not show stays in: the fit
shrinks it to zero under a prior (``PostureParams.rest_offset_prior_mps2``), so it never invents an offset it has
no data for.

Gyros of the same class carry turn-on biases of a few deg/s. GO's zero-angle update removes a constant bias within
each stride (Allseits et al. 2018), but the joint-axis fit (Seel Eq. 2: the norms of the two rates), the clock cue
and the complementary filter see it: at rest the gyro reads its bias (a zero angular-rate update), so it is taken
from the same rests and removed too. Both are removed in preparation (:func:`pipeline.prepare.prepare_leg_si`), so
every consumer sees one corrected signal, and reported in the leg's diagnostics.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.constants import G_MPS2
from pipeline.params import WALKING, PostureParams
from pipeline.signal_utils import row_norm, run_bounds, slower_than


def rest_block_starts(gyr_rps: np.ndarray, valid: np.ndarray, fs_hz: float,
                      params: PostureParams = WALKING.posture) -> tuple[np.ndarray, int]:
    """The first sample of every ``quiet_min_s`` block of the sensor's own still runs (its gyro slower than
    ``still_dps`` for at least ``quiet_min_s``, on valid samples), and the block length in samples. ``gyr_rps``:
    (N, 3) of one sensor; ``valid``: (N,) bool."""
    still = valid & slower_than(gyr_rps, params.still_dps)
    n_blk = max(int(round(params.quiet_min_s * fs_hz)), 1)
    a, b = run_bounds(still)
    # each run [a, b) holds (b - a) // n_blk whole blocks, at a, a + n_blk, ...: all runs' blocks in one array
    count = (b - a) // n_blk
    first = np.repeat(a, count)
    k = np.arange(first.shape[0]) - np.repeat(np.cumsum(count) - count, count)
    return first + k * n_blk, n_blk


def block_means(x: np.ndarray, starts: np.ndarray, n_blk: int) -> np.ndarray:
    """(K, C): the mean of ``x`` (N, C) over each block ``[s, s + n_blk)``."""
    if starts.size == 0:
        return np.zeros((0, x.shape[1]))
    # rests are a part of the session: gathering their samples is cheaper than a running sum over all of it
    return x[starts[:, None] + np.arange(n_blk)].mean(axis=1)


def posture_clusters(blocks: np.ndarray, params: PostureParams = WALKING.posture) -> tuple[np.ndarray, np.ndarray]:
    """The rest blocks (K, 3) grouped by direction: blocks within ``rest_orientation_deg`` of a group's first block
    join it (greedy, in time order). Returns the groups' median blocks (C, 3) and block counts (C,). Sway tilts a
    standing segment by a few degrees, but it is no second calibration position: an inverted pendulum's horizontal
    acceleration follows its tilt, so the specific force does not turn with the segment as gravity would. Only
    distinct postures may fix the offset across gravity."""
    cos_tol = math.cos(math.radians(params.rest_orientation_deg))
    u = blocks / row_norm(blocks)[:, None]
    label = np.full(blocks.shape[0], -1)
    n_groups = 0
    # one pass per group: its first block is the earliest one no earlier group took (the greedy rule, group by group)
    while (free := np.flatnonzero(label < 0)).size:
        join = free[u[free] @ u[free[0]] > cos_tol]
        label[free[0]] = label[join] = n_groups  # the first block always: rounding may put u.u just below cos_tol
        n_groups += 1
    counts = np.bincount(label, minlength=n_groups)
    # the median: a minority of blocks that are still but not at rest (a vehicle) cannot move it
    return np.array([np.median(blocks[label == c], axis=0) for c in range(n_groups)]), counts


def _sphere_fit(m: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Gauss-Newton for b in ``|m_c - b| = g`` (weights ``w``) under the ridge prior: ``u_c . db = |m_c - b| - g``."""
    b = np.zeros(3)
    for _ in range(4):
        d = m - b
        r = row_norm(d)
        u = d / r[:, None]
        uw = u * w[:, None]
        b = b + np.linalg.solve(uw.T @ u + ridge * np.eye(3), uw.T @ (r - G_MPS2) - ridge * b)
    return b


def fit_rest_offset(blocks: np.ndarray, params: PostureParams = WALKING.posture) -> np.ndarray:
    """(3,) [m/s^2]: the offset b with ``|m_c - b| = g`` for the rest postures ``m_c`` (the median blocks of
    :func:`posture_clusters`, weighted by their block counts), by Gauss-Newton on the linearised constraint
    ``u_c . db = |m_c - b| - g`` (``u_c``: the posture's unit direction) under a zero-mean prior of SD
    ``rest_offset_prior_mps2`` per axis. Blocks still off the sphere by more than ``force_tol`` after a first fit
    are left out and the postures formed again (a vehicle, a lift: not at rest). Zeros without blocks, or when the
    fit exceeds ``rest_offset_max_mps2`` (no data sheet allows it: not an offset). Blocks of less than half g (an
    accelerometer reading zeros, NaN) are no rests."""
    n = row_norm(blocks) if blocks.shape[0] else np.zeros(0)
    blocks = blocks[np.isfinite(n) & (n > 0.5 * G_MPS2)]
    if blocks.shape[0] == 0 or params.rest_offset_prior_mps2 <= 0:
        return np.zeros(3)
    ridge = (params.rest_block_sd_mps2 / params.rest_offset_prior_mps2) ** 2
    b = _sphere_fit(*posture_clusters(blocks, params), ridge)
    at_rest = np.abs(row_norm(blocks - b) - G_MPS2) < params.force_tol * G_MPS2
    if not at_rest.any():
        return np.zeros(3)
    if not at_rest.all():
        b = _sphere_fit(*posture_clusters(blocks[at_rest], params), ridge)
    return b if float(np.linalg.norm(b)) <= params.rest_offset_max_mps2 else np.zeros(3)


def rest_offsets(acc_mps2: np.ndarray, gyr_rps: np.ndarray, valid: np.ndarray, fs_hz: float,
                 params: PostureParams = WALKING.posture) -> tuple[np.ndarray, np.ndarray]:
    """One sensor's accelerometer offset (3,) [m/s^2] (:func:`fit_rest_offset`) and gyro bias (3,) [rad/s] from its
    rests (:func:`rest_block_starts`); subtract them from ``acc_mps2`` and ``gyr_rps``.

    The gyro bias is the median of the rest blocks' mean rates (a zero angular-rate update: at rest the gyro reads
    its bias; sway averages out within a block). Zeros without rests."""
    starts, n_blk = rest_block_starts(gyr_rps, valid, fs_hz, params)
    if starts.size == 0:
        return np.zeros(3), np.zeros(3)
    acc_offset = fit_rest_offset(block_means(acc_mps2, starts, n_blk), params)
    return acc_offset, np.median(block_means(gyr_rps, starts, n_blk), axis=0)
