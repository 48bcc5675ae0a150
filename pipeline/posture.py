"""Quiet postures and the absolute zero of the accelerometer knee angle: ONE definition for every consumer.

The accelerometer angle (Seel et al. 2014, Eq. 6-7) carries the unknown offset of the joint-plane frames: sensors
sit a few cm anterior or posterior of the segment axis, which tilts the sensor->knee directions by 10-30 deg (seen
on the real biomechZoo trial and in the simulator). Quiet upright standing fixes it: there both segments are still,
the accelerometers see gravity only (so the Eq. 7 angle is the angle between the two segments' gravity directions
in the joint plane), and the knee is ``PostureParams.standing_knee_deg`` flexed (a patient's calibration, else the
relaxed-standing assumption: healthy adults 2-6 deg). Allseits et al. 2018 (Sect. 2.4.2) zero their CF comparison
the same way. No paper gives the detection rules below.

* quiet (:func:`quiet_mask`): both segments still and their specific force within ``force_tol`` of g (each
  accelerometer's rest offset already removed in preparation, :mod:`pipeline.rest_offset`), for at least
  ``quiet_min_s`` (any posture: standing, sitting, lying); the filters trust the accelerometer angle more there;
* standing (:func:`standing_mask`): quiet, away from walking bouts, and upright: in each joint plane gravity within
  ``upright_deg`` of that segment's direction during the session's strides (:func:`gait_up_directions`: the thigh's
  mean, the shank's at the foot strikes; roughly their long axes). Sitting fails on the thigh (horizontal), lying
  on both. The order of postures in the session does not matter (the directions come from the strides, wherever
  they are);
* the zero (:func:`standing_reference`, :func:`acc_zero_deg`): the median accelerometer angle over standing, used
  by the walking policy, the CF, the KF and the EKF alike. Without standing in the session there is no zero (None):
  the callers then fall back to GO's straight-knee-before-swing level and say so.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipeline.axes import JointAxes
from pipeline.constants import G_MPS2
from pipeline.cycle_gravity import cycle_up, measured_cycles
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, PostureParams
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import long_runs, ranges_mask, slower_than


def _norm(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", x, x))


def quiet_mask(prep: PreparedLeg, params: PostureParams = WALKING.posture) -> np.ndarray:
    """(N,) bool: both segments still (slower than ``still_dps``, specific force within ``force_tol`` of g) for at
    least ``quiet_min_s``: there the accelerometer angle sees gravity only and is accurate to a degree or two."""
    thigh, shank = _still_segments(prep, params)
    return long_runs(thigh & shank, params.quiet_min_s * prep.fs_hz)


def quiet_segments(prep: PreparedLeg, params: PostureParams = WALKING.posture) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool per segment (thigh, shank): that segment alone still as :func:`quiet_mask` has it, for at least
    ``quiet_min_s``."""
    n = params.quiet_min_s * prep.fs_hz
    thigh, shank = _still_segments(prep, params)
    return long_runs(thigh, n), long_runs(shank, n)


def _still_segments(prep: PreparedLeg, params: PostureParams) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool per segment (thigh, shank): that sample still (slower than ``still_dps``, specific force within
    ``force_tol`` of g), however briefly."""
    out = []
    for gyr, acc in ((prep.gyr_thigh_rps, prep.acc_thigh_mps2), (prep.gyr_shank_rps, prep.acc_shank_mps2)):
        out.append(prep.valid & slower_than(gyr, params.still_dps)
                   & (np.abs(_norm(acc) - G_MPS2) < params.force_tol * G_MPS2))
    return out[0], out[1]


def leg_quiet(leg: LegInput) -> np.ndarray:
    """The leg's :func:`quiet_mask`: the precomputed one when the leg carries it, else computed."""
    return leg.quiet_mask if leg.quiet_mask is not None else quiet_mask(leg.prep, leg.params.posture)


def standing_mask(leg: LegInput, quiet: np.ndarray | None = None, exclude: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: quiet upright standing (module docstring). ``quiet``: the leg's :func:`quiet_mask` (default
    :func:`leg_quiet`); ``exclude``: samples that are not standing whatever they look like (default
    :func:`in_bouts`). Runs cut by the upright test or ``exclude`` shorter than ``quiet_min_s`` are dropped."""
    p = leg.params.posture
    prep = leg.prep
    quiet = leg_quiet(leg) if quiet is None else quiet
    exclude = in_bouts(leg) if exclude is None else exclude
    ups = _gait_up_directions(leg)
    if ups is None or not quiet.any():
        return np.zeros(prep.n, dtype=bool)
    stand = quiet & prep.valid & ~exclude
    for acc, up, j in ((prep.acc_thigh_mps2, ups[0], leg.axes.j1), (prep.acc_shank_mps2, ups[1], leg.axes.j2)):
        cand = np.flatnonzero(stand)  # the upright test only where it can still matter (row by row: same values)
        stand[cand] = _upright(acc[cand], up, j, p)
    return long_runs(stand, p.quiet_min_s * prep.fs_hz)


def posture_labels(leg: LegInput, quiet: np.ndarray | None = None) -> np.ndarray:
    """(N,) str per sample: ``"standing"`` (:func:`standing_mask`), ``"sitting"`` (quiet, shank upright, thigh not:
    a horizontal thigh), ``"lying"`` (quiet, neither segment upright), ``""`` elsewhere (moving, walking, or no
    strides to learn the upright directions from). The same quiet and upright tests as the zero uses."""
    prep = leg.prep
    quiet = leg_quiet(leg) if quiet is None else quiet
    out = np.full(prep.n, "", dtype=object)
    upright = upright_segments(leg)
    if upright is None:
        return out.astype(str)
    rest = quiet & prep.valid & ~in_bouts(leg)
    out[rest & ~upright[0] & upright[1]] = "sitting"
    out[rest & ~upright[0] & ~upright[1]] = "lying"
    out[standing_mask(leg, quiet)] = "standing"
    return out.astype(str)


def upright_segments(leg: LegInput) -> tuple[np.ndarray, np.ndarray] | None:
    """(N,) bool per segment (thigh, shank): its specific force within ``upright_deg`` of the segment's direction
    during gait in its joint plane (:func:`gait_up_directions`; :func:`standing_mask`'s test on every sample); None
    without strides to learn the directions from."""
    ups = _gait_up_directions(leg)
    if ups is None:
        return None
    prep = leg.prep
    out = []
    for acc, up, j in ((prep.acc_thigh_mps2, ups[0], leg.axes.j1), (prep.acc_shank_mps2, ups[1], leg.axes.j2)):
        out.append(_upright(acc, up, j, leg.params.posture))
    return out[0], out[1]


def acc_zero_deg(leg: LegInput, quiet: np.ndarray | None = None) -> tuple[float, float | None]:
    """Accelerometer-angle reading of a straight knee [deg] and the standing reading it comes from
    (:func:`standing_reference` minus ``standing_knee_deg``); ``(0.0, None)`` without standing (the angle is then
    taken as it is: the joint-plane frames' own level)."""
    ref = standing_reference(leg, leg.acc_angle_deg, quiet=quiet)
    if ref is None:
        return 0.0, None
    return float(ref - leg.params.posture.standing_knee_deg), ref


def _gait_up_directions(leg: LegInput) -> list[np.ndarray] | None:
    """:func:`gait_up_directions` over the leg's :attr:`pipeline.leg_input.LegInput.filter_strides`."""
    return gait_up_directions(leg.prep, leg.axes, leg.filter_strides, leg.params.posture.up_cycles)


def gait_up_directions(prep: PreparedLeg, axes: JointAxes, strides: Sequence[tuple[int, ...]],
                       max_cycles: int = WALKING.posture.up_cycles) -> list[np.ndarray] | None:
    """Per segment (thigh, shank), the in-plane direction of gravity during gait, pointing up, from whole strides
    (``(start, ..., stop)`` sample indices, ``start`` a foot strike); no joint-centre geometry (whose sensor->knee
    directions can be off by tens of degrees). None without strides or a consistent direction.

    The thigh's: the mean specific force over the strides (:func:`_mean_up`). Over a gait cycle a segment's mean
    acceleration is zero (its velocity is periodic), so this is gravity at the thigh's mean orientation, near its long
    axis (it swings about as far forward as back). The shank's: gravity at the foot strikes
    (:func:`pipeline.cycle_gravity.cycle_up` over up to ``max_cycles`` measured strides, evenly spread), where the
    shank stands within ~20 deg of vertical in walking and running alike. Its mean over the cycle leans back with the
    swing: in running, where the knee flexes to 90-130 deg, 24-48 deg off the shank's standing direction on an
    independent simulator, so that quiet standing failed the 45 deg upright test on one leg in sixteen and the leg
    lost its zero (25 deg low, its calibration unused). Without a measured stride (every one holds a filled hole or
    a clipped sample) the shank takes its mean over the strides too."""
    if not strides:
        return None
    arr = np.asarray([(s[0], s[-1]) for s in strides])
    thigh = _mean_up(prep, prep.acc_thigh_mps2, arr)
    shank = _strike_up(prep, arr, max_cycles)
    out = [_in_plane(thigh, axes.j1),
           _in_plane(_mean_up(prep, prep.acc_shank_mps2, arr) if shank is None else shank, axes.j2)]
    return None if out[0] is None or out[1] is None else out


def _in_plane(m: np.ndarray, j: np.ndarray) -> np.ndarray | None:
    """The unit direction of ``m`` (3,) in the plane normal to ``j``; None where less than 0.5 of it lies there (in
    g, or as a mean of unit vectors: no consistent direction, not gait)."""
    m = m - (m @ j) * j
    return None if np.linalg.norm(m) < 0.5 else m / np.linalg.norm(m)


def _mean_up(prep: PreparedLeg, acc_mps2: np.ndarray, cycles: np.ndarray) -> np.ndarray:
    """A segment's mean specific force over the valid samples of the ``cycles`` ((K, 2) start/stop), in g (3,)."""
    sel = ranges_mask(prep.n, cycles[:, 0], cycles[:, 1]) & prep.valid
    return acc_mps2[sel].mean(axis=0) / G_MPS2 if sel.any() else np.zeros(3)


def _strike_up(prep: PreparedLeg, cycles: np.ndarray, max_cycles: int) -> np.ndarray | None:
    """The shank's mean unit gravity direction (3,) at the first sample of up to ``max_cycles`` of the ``cycles``
    ((K, 2) start/stop indices) measured throughout; None without one."""
    ok = (cycles[:, 1] > cycles[:, 0]) & measured_cycles(prep, cycles)
    a, b = cycles[ok, 0], cycles[ok, 1]
    if a.size == 0:
        return None
    pick = np.unique(np.linspace(0, a.size - 1, min(a.size, max_cycles)).round().astype(int))
    up = cycle_up(prep.gyr_shank_rps, prep.acc_shank_mps2, prep.fs_hz, a[pick], b[pick])
    norm = _norm(up)
    up = up[norm > 0] / norm[norm > 0, None]
    return up.mean(axis=0) if up.size else None


def thigh_upright_at(prep: PreparedLeg, axes: JointAxes, strides: Sequence[tuple[int, ...]], idx: np.ndarray,
                     params: PostureParams = WALKING.posture) -> np.ndarray | None:
    """Per sample index in ``idx``, whether the thigh's mean specific force over the second around it (a gait
    cycle: gravity at the thigh's mean orientation) lies within ``upright_deg`` of its direction during ``strides``
    in the joint plane (the thigh's of :func:`gait_up_directions`); None without such a direction. Walking keeps a
    thigh near upright; a seated or lying leg's thigh swings far from it."""
    if not strides:
        return None
    up = _in_plane(_mean_up(prep, prep.acc_thigh_mps2, np.asarray([(s[0], s[-1]) for s in strides])), axes.j1)
    if up is None:
        return None
    idx = np.asarray(idx, dtype=int)
    half = max(int(round(0.5 * prep.fs_hz)), 1)
    acc = np.where(prep.valid[:, None], prep.acc_thigh_mps2, 0.0)
    cum = np.concatenate((np.zeros((1, 3)), np.cumsum(acc, axis=0)))
    lo, hi = np.clip(idx - half, 0, prep.n), np.clip(idx + half + 1, 0, prep.n)
    mean = cum[hi] - cum[lo]
    return _upright(mean, up, axes.j1, params)


def _upright(force: np.ndarray, up: np.ndarray, j: np.ndarray, params: PostureParams) -> np.ndarray:
    """(M,) bool per specific force (M, 3): within ``upright_deg`` of ``up`` in the joint plane normal to ``j``."""
    y = np.cross(j, up)
    return np.abs(np.degrees(np.arctan2(force @ y, force @ up))) < params.upright_deg


def in_bouts(leg: LegInput) -> np.ndarray:
    """(N,) bool: samples within ``bout_margin_s`` of a walking bout's first and last mid-swing (not standing)."""
    ev = leg.events
    margin = leg.params.posture.bout_margin_s * leg.fs_hz
    mask = np.zeros(leg.prep.n, dtype=bool)
    for b in np.unique(ev.bout[ev.bout >= 0]):
        lobes = ev.ms[ev.bout == b]
        mask[max(int(lobes[0] - margin), 0):int(lobes[-1] + margin)] = True
    return mask


def standing_reference(leg: LegInput, acc_angle_deg: np.ndarray, exclude: np.ndarray | None = None,
                       quiet: np.ndarray | None = None, standing: np.ndarray | None = None) -> float | None:
    """Accelerometer angle [deg] of quiet upright standing (median over :func:`standing_mask`), or None with less
    than ``quiet_min_s`` of standing in the session. ``standing``: that mask when the caller has it already."""
    stand = (standing_mask(leg, quiet, exclude) if standing is None else standing) & np.isfinite(acc_angle_deg)
    if stand.sum() < leg.params.posture.quiet_min_s * leg.fs_hz:
        return None
    return float(np.median(acc_angle_deg[stand]))
