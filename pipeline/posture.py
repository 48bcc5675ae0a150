"""Quiet standing and the absolute zero of the accelerometer knee angle.

The accelerometer angle (Seel et al. 2014, Eq. 6-7) carries the unknown offset of the joint-plane frames: sensors
sit a few cm anterior or posterior of the segment axis, which tilts the sensor->knee directions by 10-30 deg (seen
on the real biomechZoo trial and in the simulator). Quiet upright standing fixes it: there both segments are still,
the accelerometers see gravity only, and the knee is assumed to be ``PostureParams.standing_knee_deg`` flexed
(relaxed standing: healthy adults 2-6 deg, so absolute values carry that uncertainty). Allseits et al. 2018
(Sect. 2.4.2) zero their CF comparison the same way. No paper gives the detection rules below.

Two consumers use two definitions, kept apart so outputs stay identical (unifying them is a science change):

* the filters (KF/EKF R weighting and zero, running CF): :func:`quiet_mask` runs of ``quiet_min_s``, upright by the
  3-D angle of gravity to its mean direction over the strides (:func:`standing_mask`, :func:`acc_zero_deg`);
* the walking ``auto`` policy and the walking CF: :func:`standing_reference`, runs of ``standing_ref_min_s`` away
  from walking bouts, upright by the in-plane angle to the mean stance direction.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.constants import G_MPS2
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, PostureParams
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import row_norm, true_runs


def _norm(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", x, x))


def quiet_mask(prep: PreparedLeg, params: PostureParams = WALKING.posture) -> np.ndarray:
    """(N,) bool: both segments still (slower than ``still_dps``, specific force within ``force_tol`` of g) for at
    least ``quiet_min_s``: there the accelerometer angle sees gravity only and is accurate to a degree or two."""
    lim = math.radians(params.still_dps) ** 2
    still = prep.valid & (np.einsum("ij,ij->i", prep.gyr_thigh_rps, prep.gyr_thigh_rps) < lim)
    still &= np.einsum("ij,ij->i", prep.gyr_shank_rps, prep.gyr_shank_rps) < lim
    for acc in (prep.acc_thigh_mps2, prep.acc_shank_mps2):
        still &= np.abs(_norm(acc) - G_MPS2) < params.force_tol * G_MPS2
    out = np.zeros(prep.n, dtype=bool)
    for a, b in true_runs(still):
        if b - a >= params.quiet_min_s * prep.fs_hz:
            out[a:b] = True
    return out


def leg_quiet(leg: LegInput) -> np.ndarray:
    """The leg's :func:`quiet_mask`: the precomputed one when the leg carries it, else computed."""
    return leg.quiet_mask if leg.quiet_mask is not None else quiet_mask(leg.prep, leg.params.posture)


def gait_gravity_directions(leg: LegInput) -> tuple[np.ndarray, np.ndarray] | None:
    """Unit vectors (3,) of the mean specific force in the thigh and shank frames over the strides: during gait both
    segments swing about the vertical, so these are close to each segment's long axis (pointing up)."""
    strides = leg.filter_strides
    if not strides:
        return None
    sel = np.zeros(leg.prep.n, dtype=bool)
    for a, b in strides:
        sel[a:b] = True
    sel &= leg.prep.valid
    out = []
    for acc in (leg.prep.acc_thigh_mps2, leg.prep.acc_shank_mps2):
        m = acc[sel].mean(axis=0)
        norm = float(np.linalg.norm(m))
        if norm < 0.5 * G_MPS2:
            return None
        out.append(m / norm)
    return out[0], out[1]


def standing_mask(leg: LegInput, quiet: np.ndarray) -> np.ndarray:
    """(N,) bool: ``quiet`` samples with both segments upright, the specific force within ``upright_deg`` of its
    mean direction during gait. Tells standing from sitting and lying without the joint-centre geometry."""
    quiet = quiet.copy()
    dirs = gait_gravity_directions(leg)
    if dirs is None or not quiet.any():
        return np.zeros_like(quiet)
    cos_lim = math.cos(math.radians(leg.params.posture.upright_deg))
    for acc, u in zip((leg.prep.acc_thigh_mps2, leg.prep.acc_shank_mps2), dirs, strict=True):
        norm = np.maximum(_norm(acc), 1e-9)
        quiet &= (acc @ u) / norm > cos_lim
    return quiet


def acc_zero_deg(leg: LegInput, quiet: np.ndarray) -> tuple[float, float | None]:
    """Accelerometer-angle reading of a straight knee [deg] and the standing reading it comes from: the median
    accelerometer angle of quiet upright standing (:func:`standing_mask` of ``quiet``) minus
    ``standing_knee_deg``. The joint-centre geometry alone leaves a 10-40 deg offset. ``(0.0, None)`` with less than
    ``standing_zero_min_s`` of standing (the angle is taken as it is)."""
    p = leg.params.posture
    stand = standing_mask(leg, quiet) & np.isfinite(leg.acc_angle_deg)
    if stand.sum() < p.standing_zero_min_s * leg.fs_hz:
        return 0.0, None
    ref = np.median(leg.acc_angle_deg[stand])
    return float(ref - p.standing_knee_deg), float(ref)


def _stance_up_directions(leg: LegInput) -> list[np.ndarray] | None:
    """Per segment, the mean direction of the specific force (pointing up) in the joint plane over the stance phases
    of all strides: roughly the segment's proximal direction, since thigh and shank swing about the vertical in
    stance. Needs no joint-centre geometry (whose sensor->knee directions can be off by tens of degrees)."""
    strides = leg.events.strides
    if not strides:
        return None
    arr = np.asarray(strides)
    lens = arr[:, 1] - arr[:, 0] + 1
    # the stance indices a..t of every stride, concatenated, without a Python loop over strides
    idx = np.repeat(arr[:, 0] - np.concatenate(([0], np.cumsum(lens)[:-1])), lens) + np.arange(int(lens.sum()))
    out = []
    for acc, j in ((leg.prep.acc_thigh_mps2, leg.axes.j1), (leg.prep.acc_shank_mps2, leg.axes.j2)):
        a = acc[idx]
        f = a - np.outer(a @ j, j)
        f /= np.maximum(row_norm(f)[:, None], 1e-9)
        m = f.mean(axis=0)
        if np.linalg.norm(m) < 0.5:  # no consistent direction: not gait-like stance
            return None
        out.append(m / np.linalg.norm(m))
    return out


def in_bouts(leg: LegInput) -> np.ndarray:
    """(N,) bool: samples within ``bout_margin_s`` of a walking bout's first and last mid-swing (not standing)."""
    ev = leg.events
    margin = leg.params.posture.bout_margin_s * leg.fs_hz
    mask = np.zeros(leg.prep.n, dtype=bool)
    for b in np.unique(ev.bout[ev.bout >= 0]):
        lobes = ev.ms[ev.bout == b]
        mask[max(int(lobes[0] - margin), 0):int(lobes[-1] + margin)] = True
    return mask


def standing_reference(leg: LegInput, acc_angle_deg: np.ndarray, exclude: np.ndarray) -> float | None:
    """Accelerometer angle [deg] of quiet upright standing (median), or None when the session has none.

    Quiet: both segments slower than ``still_dps`` for at least ``standing_ref_min_s``, specific force within
    ``force_tol`` of g, not ``exclude``. Upright: in each joint plane the specific force is within ``upright_deg``
    of its mean stance direction during the session's strides (:func:`_stance_up_directions`); sitting fails on the
    thigh (horizontal)."""
    p = leg.params.posture
    prep = leg.prep
    ups = _stance_up_directions(leg)
    if ups is None:
        return None
    fs = prep.fs_hz
    speed = np.rad2deg(np.maximum(row_norm(prep.gyr_thigh_rps), row_norm(prep.gyr_shank_rps)))
    still = (speed < p.still_dps) & prep.valid & ~exclude
    for acc, up, j in ((prep.acc_thigh_mps2, ups[0], leg.axes.j1), (prep.acc_shank_mps2, ups[1], leg.axes.j2)):
        still &= np.abs(row_norm(acc) - G_MPS2) < p.force_tol * G_MPS2
        y = np.cross(j, up)
        ang = np.degrees(np.arctan2(acc @ y, acc @ up))
        still &= np.abs(ang) < p.upright_deg
    min_len = int(p.standing_ref_min_s * fs)
    keep = np.zeros_like(still)
    for a, b in true_runs(still):
        if b - a >= min_len:
            keep[a:b] = True
    vals = acc_angle_deg[keep & np.isfinite(acc_angle_deg)]
    return float(np.median(vals)) if vals.size >= min_len else None
