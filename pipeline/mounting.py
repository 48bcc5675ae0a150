"""Did a sensor's mounting change during the session? Seel's hinge axes in time windows, before against after.

Every estimator rests on one sensor-to-segment mounting per session (the knee axes of Seel et al. 2014 Eq. 2, the
joint centres of Eq. 5, the level from quiet standing). A strap re-fastened or a sensor turned on the limb half-way
through breaks that: on the simulator a shank sensor turned by 15 deg about a random axis after 2 minutes left
peak errors of 5-16 deg, 30 deg left 10-33 deg, and every stride scored for trends. The knee axis in the sensor's
frame moves with the mounting by up to the turn's angle (not at all for a turn about the axis itself, which the
gyroscope-only angle does not see either), so the hinge is fitted again in each window of ``window_s`` that moves
enough, started from the session's fit (:func:`pipeline.axes.refit_axes`), and the windows before each split point
are compared with those after it: the line the axes take before (:func:`pipeline.axes.mean_axis`) against after. A real
knee's fitted hinge also moves with the activity (3-D hip and knee: the thigh's by up to 22 deg between walking and
stairs on the simulator's ``joint_3d`` chain, the shank's by up to 7), but those windows interleave over a session,
so the two means stay close; a remount moves every later window. No paper gives these rules; the thresholds sit
above the activity spread the simulator shows. Running legs whose thigh axis is its principal rotation axis
(``RunningParams.thigh_axis``) are checked on that axis per window instead, which a 3-D knee does not move.

A turn about an axis near the knee axis barely moves the hinge, but it turns the joint-plane frames in which the
accelerometer angle (Seel Eq. 6-7) is measured, so it moves the leg's level: :func:`level_step` looks for a step
that quiet standing and the walking strides show alike (either alone also steps for other reasons).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.axes import (
    JointAxes,
    axis_angle_deg,
    fit_margin_mask,
    fit_shank_axis,
    mean_axis,
    principal_axis,
    refit_axes,
    select_fit_samples,
)
from pipeline.estimators.go import go_relative
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, AxesParams, MountingParams
from pipeline.policy import stance_offsets
from pipeline.posture import standing_mask
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import row_norm, true_runs
from pipeline.types import MountingCheck


def window_axes(prep: PreparedLeg, axes: JointAxes, fit_gyr: tuple[np.ndarray, np.ndarray],
                params: MountingParams = WALKING.mounting, principal_thigh: bool = False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window of ``params.window_s`` whose shank turns faster than ``params.moving_dps`` for at least
    ``params.min_moving_s``: its start [s] (K,), and the hinge axes refitted on it (K, 3) thigh and shank frame, on
    the gyros ``fit_gyr`` (thigh, shank (N, 3) [rad/s]: the session fit's low-passed ones,
    :func:`pipeline.walking.fit_gyros`, or the raw ones) and the measured samples away from gaps.
    ``principal_thigh``: the thigh's axis is the window's principal rotation axis over its moving samples and the
    shank's its Eq. 2 partner, as the running path finds them (``RunningParams.thigh_axis``): with a knee that is no
    hinge, the free refits wander along their shallow valley by 40-50 deg from one window to the next."""
    fs = prep.fs_hz
    win_n = max(int(round(params.window_s * fs)), 1)
    g1, g2 = fit_gyr
    usable = fit_margin_mask(prep.measured(), fs)
    moving = usable & (row_norm(g2) > np.radians(params.moving_dps))
    need = max(params.min_moving_s * fs, 10)
    bound = AxesParams(max_fit_samples=params.max_fit_samples, fit_chunks=params.fit_chunks)
    starts, j1s, j2s = [], [], []
    for a in range(0, prep.n, win_n):
        sel = moving[a:a + win_n]
        if sel.sum() < need:
            continue
        idx = a + select_fit_samples(g1[a:a + win_n], g2[a:a + win_n], sel, bound)
        if principal_thigh:
            j1 = principal_axis(g1[a:a + win_n][sel])
            j2, _ = fit_shank_axis(g1[idx], g2[idx], j1, axes.j2)
        else:
            j1, j2 = refit_axes(g1[idx], g2[idx], axes.j1, axes.j2)
        starts.append(prep.t_s[a])
        j1s.append(j1)
        j2s.append(j2)
    return np.asarray(starts, dtype=float), np.reshape(j1s, (-1, 3)), np.reshape(j2s, (-1, 3))


def check_mounting(prep: PreparedLeg, axes: JointAxes, fit_gyr: tuple[np.ndarray, np.ndarray],
                   params: MountingParams = WALKING.mounting, principal_thigh: bool = False) -> MountingCheck:
    """:class:`MountingCheck` of one prepared leg, whose session fit is ``axes`` on ``fit_gyr``. At least
    ``params.min_windows`` fitted windows on either side of a split point are needed to judge it (else the changes
    and the time are None). The axes on either side are lines (:func:`pipeline.axes.mean_axis`), so neither the
    windows' signs nor a session fit spoilt by the two mountings sway them. ``principal_thigh``: as
    :func:`window_axes`."""
    starts, j1s, j2s = window_axes(prep, axes, fit_gyr, params, principal_thigh)
    thigh_deg = params.principal_thigh_deg if principal_thigh else params.thigh_deg
    k_min = params.min_windows
    best: tuple[float, float, float] | None = None
    for k in range(k_min, starts.size - k_min + 1):
        d1 = axis_angle_deg(mean_axis(j1s[:k]), mean_axis(j1s[k:]))
        d2 = axis_angle_deg(mean_axis(j2s[:k]), mean_axis(j2s[k:]))
        if best is None or max(d1 / thigh_deg, d2 / params.shank_deg) > max(best[0] / thigh_deg,
                                                                             best[1] / params.shank_deg):
            best = (d1, d2, float(starts[k]))
    if best is None:
        return MountingCheck(thigh_deg=None, shank_deg=None, at_s=None, windows=int(starts.size), changed=False)
    return MountingCheck(thigh_deg=round(best[0], 1), shank_deg=round(best[1], 1), at_s=round(best[2], 2),
                         windows=int(starts.size), changed=best[0] > thigh_deg or best[1] > params.shank_deg)


def with_level_step(check: MountingCheck, leg: LegInput, params: MountingParams = WALKING.mounting,
                    stance_levels_deg: np.ndarray | None = None, standing: np.ndarray | None = None
                    ) -> MountingCheck:
    """``check`` (the axes') with the leg's :func:`level_step`: changed too when the step exceeds
    ``params.level_step_deg``, and then at the step's split point unless the axes found the change already."""
    step, at_s = level_step(leg, params, stance_levels_deg, standing)
    stepped = step is not None and step > params.level_step_deg
    return dataclasses.replace(check, level_step_deg=step, changed=check.changed or stepped,
                               at_s=at_s if stepped and not check.changed else check.at_s)


def level_step(leg: LegInput, params: MountingParams = WALKING.mounting, stance_levels_deg: np.ndarray | None = None,
               standing: np.ndarray | None = None) -> tuple[float | None, float | None]:
    """The largest step of the leg's level [deg] that quiet standing and the walking strides show alike, and the
    split point [s] (:func:`coherent_step`); ``(None, None)`` where no split point has both on either side.
    ``stance_levels_deg`` (per stride of ``leg.events.strides``) and ``standing`` (N,): the walking policy's, when
    it computed them (:class:`pipeline.policy.PolicyResult`); a constant added to the former changes nothing.

    Standing level: per run of quiet upright standing (:func:`pipeline.posture.standing_mask`), the median
    accelerometer angle (Seel Eq. 6-7; there it is the angle between the segments' gravity directions in the joint
    plane). Walking level: per stride, the mean of (accelerometer angle - GO) over its calm mid-stance
    (:func:`pipeline.policy.stance_offsets`; GO's zero sits at the knee's minimum before swing, Allseits et al.
    2018). Both rest on the joint-plane frames, which turn with a sensor turned on its segment; the patient's own
    standing and gait change one at a time."""
    strides = leg.events.strides
    runs = true_runs(standing_mask(leg) if standing is None else standing)
    if len(runs) < 2 or len(strides) < 2 * params.level_min_strides:
        return None, None
    t_s = leg.prep.t_s
    angle = leg.acc_angle_deg
    stand_t = np.array([t_s[a] for a, _ in runs])
    stand_deg = np.array([np.nanmedian(angle[a:b]) for a, b in runs])
    offs = stance_offsets(leg, go_relative(leg)[0], strides)[0] if stance_levels_deg is None else stance_levels_deg
    stride_t = np.array([t_s[a] for a, _, _ in strides])
    stood, ok = np.isfinite(stand_deg), np.isfinite(offs)
    return coherent_step(stand_t[stood], stand_deg[stood], stride_t[ok], offs[ok], params)


def coherent_step(stand_t_s: np.ndarray, stand_deg: np.ndarray, stride_t_s: np.ndarray, stride_deg: np.ndarray,
                  params: MountingParams = WALKING.mounting) -> tuple[float | None, float | None]:
    """The largest step [deg] shared by two level series, and where [s]. ``stand_*``: one level per standing run
    (start time, level); ``stride_*``: one per stride, both sorted by time. At each split point (the start of a
    standing run or of a walking bout, i.e. a stride more than 2.5 median stride periods after the one before) with
    a standing run and ``level_min_strides`` strides on either side, each series steps by the difference of its
    medians after and before; the shared step is the smaller of the two when they share their sign and agree within
    ``level_agree_deg``, else 0. ``(None, None)`` without such a split point."""
    if stand_t_s.size < 2 or stride_t_s.size < 2 * params.level_min_strides:
        return None, None
    periods = np.diff(stride_t_s)
    bout_starts = stride_t_s[1:][periods > 2.5 * np.median(periods)]
    best: tuple[float, float] | None = None
    for t in np.unique(np.concatenate([stand_t_s[1:], bout_starts])):
        ks, kw = int(np.searchsorted(stand_t_s, t)), int(np.searchsorted(stride_t_s, t))
        if not 0 < ks < stand_t_s.size or min(kw, stride_t_s.size - kw) < params.level_min_strides:
            continue
        d_stand = float(np.median(stand_deg[ks:]) - np.median(stand_deg[:ks]))
        d_walk = float(np.median(stride_deg[kw:]) - np.median(stride_deg[:kw]))
        shared = min(abs(d_stand), abs(d_walk)) if d_stand * d_walk > 0 and \
            abs(d_stand - d_walk) <= params.level_agree_deg else 0.0
        if best is None or shared > best[0]:
            best = (shared, float(t))
    return (None, None) if best is None else (round(best[0], 1), round(best[1], 2))
