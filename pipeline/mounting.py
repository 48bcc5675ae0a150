"""Did a sensor's mounting change during the session? Seel's hinge axes in time windows, before against after.

Every estimator rests on one sensor-to-segment mounting per session (the knee axes of Seel et al. 2014 Eq. 2, the
joint centres of Eq. 5, the level from quiet standing). A strap re-fastened or a sensor turned on the limb half-way
through breaks that: on the simulator a shank sensor turned by 15 deg about a random axis after 2 minutes left
peak errors of 5-16 deg, 30 deg left 10-33 deg, and every stride scored for trends. The knee axis in the sensor's
frame moves with the mounting by up to the turn's angle (not at all for a turn about the axis itself, which the
gyroscope-only angle does not see either), so the hinge is fitted again in each window of ``window_s`` that moves
enough, started from the session's fit (:func:`pipeline.axes.refit_axes`), and the windows before each split point
are compared with those after it: the direction the axis takes before (a sign-aligned mean) against after. A real
knee's fitted hinge also moves with the activity (3-D hip and knee: the thigh's by up to 22 deg between walking and
stairs on the simulator's ``joint_3d`` chain, the shank's by up to 7), but those windows interleave over a session,
so the two means stay close; a remount moves every later window. No paper gives these rules; the thresholds sit
above the activity spread the simulator shows.
"""

from __future__ import annotations

import numpy as np

from pipeline.axes import JointAxes, refit_axes, select_fit_samples
from pipeline.params import WALKING, AxesParams, MountingParams
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import row_norm
from pipeline.types import MountingCheck


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))))))


def _mean_axis(axes: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Sign-aligned sum of unit axes (K, 3) (each turned towards ``ref``)."""
    signs = np.where(axes @ ref < 0, -1.0, 1.0)
    return (axes * signs[:, None]).sum(axis=0)


def window_axes(prep: PreparedLeg, axes: JointAxes, params: MountingParams = WALKING.mounting
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window of ``params.window_s`` whose shank turns faster than ``params.moving_dps`` for at least
    ``params.min_moving_s``: its start [s] (K,), and the hinge axes refitted on it (K, 3) thigh and shank frame."""
    fs = prep.fs_hz
    w = max(int(round(params.window_s * fs)), 1)
    g1, g2 = prep.gyr_thigh_rps, prep.gyr_shank_rps
    moving = prep.valid & (row_norm(np.where(prep.valid[:, None], g2, 0.0)) > np.radians(params.moving_dps))
    starts, j1s, j2s = [], [], []
    bound = AxesParams(max_fit_samples=params.max_fit_samples, fit_chunks=params.fit_chunks)
    for a in range(0, prep.n, w):
        sel = moving[a:a + w]
        if sel.sum() < params.min_moving_s * fs:
            continue
        idx = a + select_fit_samples(g1[a:a + w], g2[a:a + w], sel, bound)
        j1, j2 = refit_axes(g1[idx], g2[idx], axes.j1, axes.j2)
        starts.append(prep.t_s[a])
        j1s.append(j1)
        j2s.append(j2)
    return np.asarray(starts, dtype=float), np.reshape(j1s, (-1, 3)), np.reshape(j2s, (-1, 3))


def check_mounting(prep: PreparedLeg, axes: JointAxes, params: MountingParams = WALKING.mounting) -> MountingCheck:
    """:class:`MountingCheck` of one prepared leg, whose session fit is ``axes``. At least ``params.min_windows``
    fitted windows on either side of a split point are needed to judge it."""
    starts, j1s, j2s = window_axes(prep, axes, params)
    k_min = params.min_windows
    best = (0.0, 0.0, float("nan"))
    for k in range(k_min, starts.size - k_min + 1):
        d1 = _angle_deg(_mean_axis(j1s[:k], axes.j1), _mean_axis(j1s[k:], axes.j1))
        d2 = _angle_deg(_mean_axis(j2s[:k], axes.j2), _mean_axis(j2s[k:], axes.j2))
        if max(d1 / params.thigh_deg, d2 / params.shank_deg) > max(best[0] / params.thigh_deg,
                                                                       best[1] / params.shank_deg):
            best = (d1, d2, float(starts[k]))
    changed = best[0] > params.thigh_deg or best[1] > params.shank_deg
    return MountingCheck(thigh_deg=round(best[0], 1), shank_deg=round(best[1], 1), at_s=best[2],
                         windows=int(starts.size), changed=changed)
