"""The absolute level of a walk from the quiet standing around it: the knee rate integrated from one standing period
to the next, its drift removed so that it meets the static angle at both ends.

In quiet standing the accelerometer angle (Seel et al. 2014, Eq. 7) sees gravity only: it needs no joint centres,
no lever-arm terms and no thigh-shank clock, and its one unknown, the constant offset of the joint-plane frames, is
fixed there (:mod:`pipeline.posture`). In gait it sees every acceleration as well, so a per-stride level taken from
it in mid-stance (:func:`pipeline.policy.stance_offsets`) carries whatever the joint-centre fit and the clock
alignment got wrong, leg by leg. The gyroscopes carry the level from standing into the walk instead: the knee rate
(Seel Eq. 4, the flexion rate about the fitted axes) integrated from the end of the standing before a walk reaches
the start of the standing after it with the integral of the gyro's residual bias, which a linear term removes, as
the two-point drift correction between static periods of strapdown integration (the zero-velocity updates of
foot-mounted inertial navigation; Potter et al. 2022 correct lower-limb kinematics with them). The knee's angle
about a fitted hinge axis is not an exact integral of a 3-D rotation, but over a periodic gait cycle its error
returns to where it began, and what is left grows like a drift: the same line takes it. A turn of the body does not
return (:func:`bridged_angle`), so it ends a bridge.

Used where the run between the two standing periods is wholly measured, holds no turn, is shorter than
``FusionParams.bridge_max_span_s`` and its drift stays below ``FusionParams.bridge_max_drift_deg``. Not across a
hole filled from the neighbouring strides (:func:`pipeline.prepare.periodic_fill`): the integral would take their
change over the hole, and crossing the fills of 156 ms holes moved two of ten legs of this repository's simulator
under 5 % packet loss by 3.4-3.5 deg (to -2.0 and -5.4 deg of peak error). Elsewhere the policy keeps its strides'
mid-stance levels (from each stride's gravity or its neighbours', or the accelerometer angle), which this one
checks (:func:`pipeline.policy.fuse`, :func:`level_check`).

A walk broken by a hole or a turn is not integrated from either end alone either: without the far end nothing
checks or removes the drift, which need not be small. On an independent simulator (3-D hips and knees, gyro biases
up to 1 deg/s) pieces of 4 s from one end drifted 7-11 deg, and legs under 5 % bursty packet loss, checked by such
pieces, took levels 4-8 deg off (peaks -9 deg in trends) from strides whose own gravity levels were right.
"""

from __future__ import annotations

import numpy as np

from pipeline.axes import mean_up
from pipeline.estimators.go import integrate_runs
from pipeline.leg_input import LegInput
from pipeline.params import FusionParams
from pipeline.phases import midstance_bounds
from pipeline.signal_utils import run_bounds, segment_sums


def heading_deg(leg: LegInput) -> np.ndarray:
    """(N,) the thigh's rotation [deg] about its mean up direction (:func:`pipeline.axes.mean_up`), integrated from the
    session's start (NaN-free: holes add nothing). The thigh's long axis stays within ~30 deg of vertical in gait, so a
    turn of the body shows in it at cos 30 deg or more, while straight walking only rocks it by the hip's rotation (+-5
    deg)."""
    prep = leg.prep
    up = mean_up(prep.acc_thigh_mps2, prep.valid)
    if up is None:
        return np.zeros(prep.n)
    rate = np.rad2deg(prep.gyr_thigh_rps @ up)
    rate = np.where(prep.valid & np.isfinite(rate), rate, 0.0)
    return integrate_runs(rate, prep.fs_hz, np.ones(prep.n, dtype=bool))


def bridged_angle(leg: LegInput, zero_deg: float, params: FusionParams, standing: np.ndarray) -> np.ndarray:
    """(N,) absolute knee angle [deg] between quiet standing periods (NaN elsewhere): the knee rate ``leg.rate_dps``
    integrated from the standing before each run of motion to the standing after it, drift-corrected linearly so that
    it meets the static accelerometer angle (``leg.acc_angle_deg - zero_deg``, median over ``params.bridge_anchor_s``
    of standing at either end) at both ends; not where the run holds a sample that is not measured (a hole, filled
    or not) or the body turns in it (``params.bridge_max_turn_deg``). ``zero_deg``: the accelerometer angle of a
    straight knee (:func:`pipeline.posture.acc_zero_deg`); ``standing``: the leg's quiet standing
    (:func:`pipeline.posture.standing_mask`).

    Anchors are standing only: the zero is defined there, while a seated thigh's skin shifts with the flexion and
    the static angle at 90 deg is the most sensitive to an axis error. A turn of the body is a rotation about the
    vertical that the fitted thigh and shank axes, levelled to within a few deg, take in unequally: a 180 deg turn
    with axes 4 deg apart adds a step of up to 180 sin 4 deg = 12 deg that no drift line removes."""
    prep = leg.prep
    n = prep.n
    out = np.full(n, np.nan)
    stand = standing & np.isfinite(leg.acc_angle_deg)
    starts, stops = run_bounds(stand)
    if starts.size < 2:
        return out
    fs = prep.fs_hz
    anchor = max(int(round(params.bridge_anchor_s * fs)), 1)
    rate = np.where(prep.measured(), leg.rate_dps, np.nan)
    heading = heading_deg(leg)
    for k in range(starts.size - 1):
        a, b = int(stops[k]), int(starts[k + 1])  # motion runs over [a, b): last standing sample a - 1, next b
        if b - a < 2 or (b - a) / fs > params.bridge_max_span_s:
            continue
        seg = rate[a - 1:b + 1]
        turn = heading[a - 1:b + 1]
        if not np.isfinite(seg).all() or np.abs(turn - turn[0]).max() > params.bridge_max_turn_deg:
            continue  # a hole or a turn inside
        lvl_a = float(np.median(leg.acc_angle_deg[max(a - anchor, int(starts[k])):a])) - zero_deg
        lvl_b = float(np.median(leg.acc_angle_deg[b:min(b + anchor, int(stops[k + 1]))])) - zero_deg
        theta = lvl_a + integrate_runs(seg, fs, np.ones(seg.size, dtype=bool))
        drift = theta[-1] - lvl_b
        if abs(drift) <= params.bridge_max_drift_deg:
            out[a - 1:b + 1] = theta - drift * np.linspace(0.0, 1.0, theta.size)
    return out


def stride_means(d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The mean of ``d`` (N,) over each range ``[lo, hi)``, NaN where the range holds a non-finite value."""
    ok = np.isfinite(d)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(segment_sums(ok, lo, hi) == hi - lo, segment_sums(np.where(ok, d, 0.0), lo, hi) / (hi - lo),
                        np.nan)


def stride_check(d: np.ndarray, lo: np.ndarray, hi: np.ndarray, min_strides: int) -> float | None:
    """The median over the ranges ``[lo, hi)`` of ``d``'s (N,) mean where ``d`` is finite throughout a range
    (:func:`stride_means`); None with fewer than ``min_strides`` such ranges. The check of a level against the
    bridged one."""
    means = stride_means(d, lo, hi)
    means = means[np.isfinite(means)]
    return float(np.median(means)) if means.size >= min_strides else None


def bridged_offsets(leg: LegInput, go_rel: np.ndarray, bridged: np.ndarray, strides: list[tuple[int, int, int]]
                    ) -> np.ndarray:
    """Per stride, the mean of (bridged angle - GO) [deg] over the stride's mid-stance (the window of
    :func:`pipeline.policy.stance_offsets`), NaN where the stride is not bridged throughout that window."""
    if not strides:
        return np.zeros(0)
    lo, hi = midstance_bounds(strides, leg.params.fusion.midstance_window)
    return stride_means(bridged - go_rel, lo, hi)


def level_check(leg: LegInput, angle_deg: np.ndarray, zero_deg: float, params: FusionParams, standing: np.ndarray
                ) -> float | None:
    """The bridged angle (:func:`bridged_angle`) minus ``angle_deg`` (N,) [deg]: the median over
    the leg's strides of each stride's mean difference, where both are finite throughout it; None with fewer than
    ``params.bridge_min_strides`` such strides. The check of a running leg's level (the walking policy checks its
    per-stride offsets the same way, :func:`pipeline.policy.fuse`)."""
    strides = leg.events.strides
    if len(strides) < params.bridge_min_strides:
        return None
    arr = np.asarray(strides)
    return stride_check(bridged_angle(leg, zero_deg, params, standing) - angle_deg,
                        arr[:, 0], arr[:, 2] + 1, params.bridge_min_strides)
