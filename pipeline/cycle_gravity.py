"""Gravity over whole gait cycles: each segment's inclination at every foot strike, free of impacts and lever arms
(walking strides and running cycles alike).

Over one gait cycle of steady locomotion every point of a segment returns to the same velocity, so its linear
acceleration integrates to zero and the mean specific force over the cycle, expressed in a frame that does not rotate,
is gravity alone (Newton: ``mean(f) = mean(a) + g = (v(T) - v(0)) / T + g``). The gyroscope carries the sensor frame of
the cycle's first sample through the cycle (strapdown integration; over one cycle a 1 deg/s bias turns it by less than
a degree), so the mean of ``R(t) f(t)`` is the direction of "up" in the sensor frame at the foot strike. Impacts,
lever-arm (tangential and centripetal) accelerations and soft-tissue ringing are all part of ``a`` and cancel; no joint
centre is needed. A change of pace tilts the estimate of both segments by the same world angle, which cancels in the
knee angle (the difference of the two segments' rotations about the joint axis).

The knee angle at the strike follows from the two segments' rotations about their joint axes since quiet standing
(Seel et al. 2014, Eq. 6-7: the angle between the two segments' gravity directions in the joint plane, here with
gravity taken from the cycle mean instead of the instantaneous reading).
"""

from __future__ import annotations

import numpy as np

from pipeline.axes import mean_up
from pipeline.constants import G_MPS2
from pipeline.leg_input import LegInput
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import row_norm, segment_sums
from pipeline.strapdown import CycleFrames, chained_frames, cycle_blocks, rotate_padded


def cycle_up(gyr_rps: np.ndarray, acc_mps2: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray
             ) -> np.ndarray:
    """Per cycle ``[starts[k], ends[k])`` the mean specific force over the cycle in the sensor frame of its first
    sample, (K, 3) [m/s^2] (module docstring; each sample's frame from :func:`pipeline.strapdown.chained_frames`).
    ``gyr_rps`` (N, 3), ``acc_mps2`` (N, 3) on a uniform grid at ``fs_hz``; the cycles must hold finite samples
    only."""
    starts = np.asarray(starts, dtype=int)
    ends = np.asarray(ends, dtype=int)
    out = np.zeros((starts.size, 3))
    for group in cycle_blocks(starts, ends):
        out[group] = _cycle_gravity(gyr_rps, acc_mps2, fs_hz, starts[group], ends[group])[0]
    return out


def _cycle_gravity(gyr_rps: np.ndarray, acc_mps2: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray
                   ) -> tuple[np.ndarray, CycleFrames]:
    """:func:`cycle_up` and the frames it was found with (:func:`pipeline.strapdown.chained_frames`)."""
    f = chained_frames(gyr_rps, fs_hz, starts, ends)
    # each sample's force turned into its cycle's first frame, summed over the cycle (the padding adds nothing)
    total = rotate_padded(f.q, f.padded(acc_mps2)).sum(axis=1).T
    return total / np.maximum(f.lengths, 1)[:, None], f


def up_at_samples(gyr_rps: np.ndarray, acc_mps2: np.ndarray, fs_hz: float, starts: np.ndarray, ends: np.ndarray,
                  lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cycle-mean gravity of each cycle ``[starts[k], ends[k])`` carried by the gyro to each of its samples in
    ``[lo[k], hi[k])``: ``(up, idx, owner, norm)``, gravity in each such sample's sensor frame (M, 3) [m/s^2], the
    sample indices (M,), the cycle each belongs to (M,) and the norm of each cycle's mean force (K,) (as
    :func:`cycle_up`)."""
    starts, ends = np.asarray(starts, dtype=int), np.asarray(ends, dtype=int)
    lo, hi = np.asarray(lo, dtype=int), np.asarray(hi, dtype=int)
    norm = np.zeros(starts.size)
    ups, idxs, owners = [np.zeros((0, 3))], [np.zeros(0, dtype=int)], [np.zeros(0, dtype=int)]
    for group in cycle_blocks(starts, ends):
        up0, f = _cycle_gravity(gyr_rps, acc_mps2, fs_hz, starts[group], ends[group])
        norm[group] = row_norm(up0)
        sel = (f.idx >= lo[group][f.owner]) & (f.idx < hi[group][f.owner])
        owner, pos = f.owner[sel], f.pos[sel]
        inverse = f.q[:, pos, owner] * np.array([1.0, -1.0, -1.0, -1.0])[:, None]  # the first frame into each sample's
        ups.append(rotate_padded(inverse, up0[owner].T).T)
        idxs.append(f.idx[sel])
        owners.append(group[owner])
    return np.concatenate(ups), np.concatenate(idxs), np.concatenate(owners), norm


def plane_angle_rad(up: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Angle (K,) [rad] of the vectors ``up`` (K, 3) about the unit axis ``j`` (3,), from a fixed direction normal
    to it: a rotation of the segment by +x about ``j`` turns the world's up in the sensor frame by -x."""
    e1 = np.cross(j, [1.0, 0.0, 0.0] if abs(j[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(j, e1)
    u = np.atleast_2d(up)
    return np.arctan2(u @ e2, u @ e1)


def knee_from_gravity_deg(up_thigh: np.ndarray, up_shank: np.ndarray, stand_thigh: np.ndarray,
                          stand_shank: np.ndarray, j1: np.ndarray, j2: np.ndarray, standing_knee_deg: float
                          ) -> np.ndarray:
    """Knee flexion (K,) [deg] from each segment's up direction (K, 3) and its quiet-standing up direction (3,):
    the thigh's rotation about ``j1`` since standing minus the shank's about ``j2``, plus the standing flexion (the
    sign convention of the knee rate ``g1.j1 - g2.j2``)."""
    def turned(up: np.ndarray, stand: np.ndarray, j: np.ndarray) -> np.ndarray:
        d = plane_angle_rad(stand, j)[0] - plane_angle_rad(up, j)
        return np.angle(np.exp(1j * d))

    valid = (row_norm(np.atleast_2d(up_thigh)) > 0) & (row_norm(np.atleast_2d(up_shank)) > 0)
    knee = np.rad2deg(turned(up_thigh, stand_thigh, j1) - turned(up_shank, stand_shank, j2)) + standing_knee_deg
    return np.where(valid, knee, np.nan)


def _standing_ups(prep: PreparedLeg, standing: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Each sensor's up direction in quiet standing (``standing`` mask), or None (:func:`pipeline.axes.mean_up`)."""
    stand = standing & prep.valid
    return mean_up(prep.acc_thigh_mps2, stand), mean_up(prep.acc_shank_mps2, stand)


def measured_cycles(prep: PreparedLeg, cycles: np.ndarray) -> np.ndarray:
    """(K,) bool per ``[start, stop)`` cycle (K, 2): all its samples measured (:meth:`PreparedLeg.measured`: valid,
    not filled from the neighbouring strides) and none saturated."""
    return segment_sums(prep.saturated | ~prep.measured(), cycles[:, 0], cycles[:, 1]) == 0


def cycle_knee_deg(leg: LegInput, standing: np.ndarray, max_off_g_mps2: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per running cycle of ``leg`` (``[start, stop)`` from foot strike to foot strike) whose samples are all
    measured (no fill, no saturation): its first sample, its stop and the knee flexion at the first from the
    cycle-mean gravity [deg] (:func:`knee_from_gravity_deg`, quiet standing's ``standing`` mask giving each sensor's
    standing up direction). A cycle whose mean specific force differs from g by more than ``max_off_g_mps2`` on
    either sensor (a jump, a step up: the vertical velocity did not return) gives none."""
    prep = leg.prep if leg.unfiltered is None else leg.unfiltered
    cyc = np.asarray(leg.running_cycles, dtype=int).reshape(-1, 2)
    stand_thigh, stand_shank = _standing_ups(prep, standing)
    if cyc.size == 0 or stand_thigh is None or stand_shank is None:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int), np.zeros(0)
    keep = measured_cycles(prep, cyc)
    a, b = cyc[keep, 0], cyc[keep, 1]
    up1 = cycle_up(prep.gyr_thigh_rps, prep.acc_thigh_mps2, prep.fs_hz, a, b)
    up2 = cycle_up(prep.gyr_shank_rps, prep.acc_shank_mps2, prep.fs_hz, a, b)
    ok = (np.abs(row_norm(up1) - G_MPS2) <= max_off_g_mps2) & (np.abs(row_norm(up2) - G_MPS2) <= max_off_g_mps2)
    knee = knee_from_gravity_deg(up1[ok], up2[ok], stand_thigh, stand_shank, leg.axes.j1, leg.axes.j2,
                                 leg.params.posture.standing_knee_deg)
    return a[ok], b[ok], knee


def window_knee_deg(leg: LegInput, standing: np.ndarray, max_off_g_mps2: float, cycles: np.ndarray,
                    lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) knee flexion [deg] from the cycle-mean gravity on the samples ``[lo[k], hi[k])`` of each cycle
    ``cycles[k]`` (``[start, stop)`` from foot strike to foot strike) whose samples are all measured and whose mean
    force lies within ``max_off_g_mps2`` of g on both sensors; NaN elsewhere. Each sample's gravity direction is the
    cycle's, carried there by the gyro (:func:`up_at_samples`); read where both segments stand near vertical (walking's
    mid-stance) the angle between their joint-plane projections is least coupled to the hip's and knee's rotations
    out of the sagittal plane (at a heel strike the thigh leans 20-30 deg forward, and a 10-15 deg ab/adduction or
    axial rotation then moves its projected inclination by 0.3-0.8 deg)."""
    prep = leg.prep
    out = np.full(prep.n, np.nan)
    cyc = np.asarray(cycles, dtype=int).reshape(-1, 2)
    stand_thigh, stand_shank = _standing_ups(prep, standing)
    if cyc.size == 0 or stand_thigh is None or stand_shank is None:
        return out
    keep = measured_cycles(prep, cyc)
    a, b, lo, hi = cyc[keep, 0], cyc[keep, 1], np.asarray(lo)[keep], np.asarray(hi)[keep]
    up1, idx, owner, n1 = up_at_samples(prep.gyr_thigh_rps, prep.acc_thigh_mps2, prep.fs_hz, a, b, lo, hi)
    up2, _, _, n2 = up_at_samples(prep.gyr_shank_rps, prep.acc_shank_mps2, prep.fs_hz, a, b, lo, hi)
    ok = ((np.abs(n1 - G_MPS2) <= max_off_g_mps2) & (np.abs(n2 - G_MPS2) <= max_off_g_mps2))[owner]
    out[idx[ok]] = knee_from_gravity_deg(up1[ok], up2[ok], stand_thigh, stand_shank, leg.axes.j1, leg.axes.j2,
                                         leg.params.posture.standing_knee_deg)
    return out
