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
above the activity spread the simulator shows.
"""

from __future__ import annotations

import numpy as np

from pipeline.axes import JointAxes, axis_angle_deg, fit_margin_mask, mean_axis, refit_axes, select_fit_samples
from pipeline.params import WALKING, AxesParams, MountingParams
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import row_norm
from pipeline.types import MountingCheck


def window_axes(prep: PreparedLeg, axes: JointAxes, fit_gyr: tuple[np.ndarray, np.ndarray],
                params: MountingParams = WALKING.mounting) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window of ``params.window_s`` whose shank turns faster than ``params.moving_dps`` for at least
    ``params.min_moving_s``: its start [s] (K,), and the hinge axes refitted on it (K, 3) thigh and shank frame, on
    the gyros ``fit_gyr`` (thigh, shank (N, 3) [rad/s]: the session fit's low-passed ones,
    :func:`pipeline.walking.fit_gyros`, or the raw ones) and the measured samples away from gaps."""
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
        j1, j2 = refit_axes(g1[idx], g2[idx], axes.j1, axes.j2)
        starts.append(prep.t_s[a])
        j1s.append(j1)
        j2s.append(j2)
    return np.asarray(starts, dtype=float), np.reshape(j1s, (-1, 3)), np.reshape(j2s, (-1, 3))


def check_mounting(prep: PreparedLeg, axes: JointAxes, fit_gyr: tuple[np.ndarray, np.ndarray],
                   params: MountingParams = WALKING.mounting) -> MountingCheck:
    """:class:`MountingCheck` of one prepared leg, whose session fit is ``axes`` on ``fit_gyr``. At least
    ``params.min_windows`` fitted windows on either side of a split point are needed to judge it (else the changes
    and the time are None). The axes on either side are lines (:func:`pipeline.axes.mean_axis`), so neither the
    windows' signs nor a session fit spoilt by the two mountings sway them."""
    starts, j1s, j2s = window_axes(prep, axes, fit_gyr, params)
    k_min = params.min_windows
    best: tuple[float, float, float] | None = None
    for k in range(k_min, starts.size - k_min + 1):
        d1 = axis_angle_deg(mean_axis(j1s[:k]), mean_axis(j1s[k:]))
        d2 = axis_angle_deg(mean_axis(j2s[:k]), mean_axis(j2s[k:]))
        if best is None or max(d1 / params.thigh_deg, d2 / params.shank_deg) > max(best[0] / params.thigh_deg,
                                                                                    best[1] / params.shank_deg):
            best = (d1, d2, float(starts[k]))
    if best is None:
        return MountingCheck(thigh_deg=None, shank_deg=None, at_s=None, windows=int(starts.size), changed=False)
    return MountingCheck(thigh_deg=round(best[0], 1), shank_deg=round(best[1], 1), at_s=round(best[2], 2),
                         windows=int(starts.size), changed=best[0] > params.thigh_deg or best[1] > params.shank_deg)
