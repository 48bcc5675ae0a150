"""Sensor-label checks: is the "thigh" sensor on the thigh, and is each thigh paired with its own leg's shank?

Thigh and shank swapped within a leg: in gait the shank swings faster than the thigh (sagittal swing peaks ~350 vs
~150 deg/s: the shank's rotation is the thigh's plus the knee's, Winter 2009, Ch. 4). The shank over thigh swing-rate
ratio is 1.9-2.7 with the right labels (simulator axes; 2.4 on the real biomechZoo Xsens trial) and 0.3-0.45 with
swapped ones, so the swap is detected and corrected by exchanging the two streams. The heel-strike impact would seem
a second witness (the shank takes it first; Lafortune 1991) and it is on the simulator, but on the real Xsens trial
the thigh's specific force changes faster than the shank's (ratio 0.64-0.68: soft tissue and sensor filtering), so
it is reported, never decisive.

Thigh and shank told apart by where the knee is: the swing-rate rule reads gait, and exercises that lift the thigh
faster than gait swings the shank (high knees, marching, step-ups) make it read a right order as exchanged. The
joint-centre fit (Seel et al. 2014, Eq. 5) gives each sensor's position relative to the knee centre in its own frame,
and the segment's mean specific force points up along it (upright most of any session with gait): a thigh sensor
lies above the knee, a shank sensor below it, whatever the movement. The rule is relative: the sensor taken for
the thigh must lie higher above the knee than the one taken for the shank (:func:`segments_by_centre`). It confirms
or vetoes an exchange the rates made, once the leg has been processed.

Thighs swapped between the legs: each knee is a hinge about a fixed centre, so the two sensors of one leg satisfy the
rigid-body constraint of Seel et al. 2014 Eq. 5 (same knee-centre acceleration seen from both segments); a thigh of
the other leg does not (its centre residual is 3-6x larger). When a leg's residual is suspicious, the swapped pairing
is fitted too and taken when clearly better (:func:`swapped_pairing_better`).

Legs swapped (all four sensors): one leg's two IMUs are the same whichever side they are on in the sagittal plane
(the mounting is arbitrary and the knee bends the same way). The frontal plane tells the sides apart: in loading
response and early mid-stance the body's weight moves over the stance foot (the centre of mass shifts towards the
stance limb, peaking at mid-stance; the hip adducts, Kadaba et al. 1990; Winter 2009, Ch. 5), so the stance
thigh's top moves laterally over its knee: a rotation about the walking direction whose sense is mirrored between
the legs. Seen in the leg's own frame (the knee axis ``j1``, which points the same way on both legs, and the
vertical), the left thigh turns one way and the right the other (:func:`weight_shift_dps`). When both legs turn the
other leg's way, the thighs are on the other sides: the labels of all four sensors, or of the two thighs, are in
doubt (:func:`side_verdict`). A planar walker (no frontal motion) and a leg whose thigh barely shifts leave it
undecided; nothing is ever corrected on this cue alone: the strides are kept out of trends and the session says
why (``side_in_doubt``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.axes import mean_up
from pipeline.params import WALKING, AssignmentParams
from pipeline.prepare import SI, to_si
from pipeline.signal_utils import ranges_mask, row_norm, segment_sums
from pipeline.types import RawSensorStream


@dataclass(frozen=True)
class SegmentCheck:
    """Shank over thigh swing rate and impact ratios of one leg, and the verdict from the rate: ``"as_labelled"``,
    ``"swapped"`` (thigh and shank exchanged) or ``"undecided"`` (no gait to tell)."""

    rate_ratio: float
    impact_ratio: float
    verdict: str


def _swing_and_impact(stream: RawSensorStream, params: AssignmentParams, si: SI | None = None
                      ) -> tuple[float, float]:
    """Swing rate [deg/s] (a high percentile of the gyro norm) and impact [m/s^3] (the same percentile of the
    specific force's rate of change) of one sensor; ``si``: its :func:`pipeline.prepare.to_si` when already known."""
    t, gyr, acc = to_si(stream) if si is None else si
    if t.shape[0] < 3:
        return float("nan"), float("nan")
    rate = float(np.percentile(np.rad2deg(row_norm(gyr)), params.rate_percentile))
    jerk = row_norm(np.diff(acc, axis=0)) / np.maximum(np.diff(t), 1e-6)
    return rate, float(np.percentile(jerk, params.rate_percentile + 0.5 * (100.0 - params.rate_percentile)))


def check_segments(thigh: RawSensorStream, shank: RawSensorStream,
                   params: AssignmentParams = WALKING.assignment, si: tuple[SI, SI] | None = None) -> SegmentCheck:
    """Whether the streams labelled thigh and shank of one leg are on those segments (module docstring). ``si``: the
    two streams' :func:`pipeline.prepare.to_si`, when the caller has them (the same values, converted once)."""
    r1, i1 = _swing_and_impact(thigh, params, None if si is None else si[0])
    r2, i2 = _swing_and_impact(shank, params, None if si is None else si[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        # numpy division: a sensor that never moves (r1 = 0) gives inf/nan and no verdict, not an exception
        rate, impact = np.float64(r2) / r1, np.float64(i2) / i1
    if not np.isfinite(rate):
        return SegmentCheck(float(rate), float(impact), "undecided")
    if rate < params.swap_ratio:
        verdict = "swapped"
    elif rate > params.keep_ratio:
        verdict = "as_labelled"
    else:
        verdict = "undecided"
    return SegmentCheck(round(float(rate), 3), round(float(impact), 3), verdict)


def centre_heights_m(o1_m: np.ndarray, o2_m: np.ndarray, acc_thigh_mps2: np.ndarray, acc_shank_mps2: np.ndarray,
                     valid: np.ndarray) -> tuple[float, float]:
    """How far the thigh and the shank sensor lie above the knee centre [m]: their positions relative to it
    (``o1_m``, ``o2_m`` (3,), Seel Eq. 5, each in its sensor's frame) along the segment's mean specific force over
    the ``valid`` samples (``acc_*`` (N, 3) [m/s^2]), which points up the segment wherever it is mostly upright. NaN
    without a valid sample or a specific force."""
    out = []
    for o, acc in ((o1_m, acc_thigh_mps2), (o2_m, acc_shank_mps2)):
        up = mean_up(acc, valid)
        out.append(float("nan") if up is None else float(np.asarray(o) @ up))
    return out[0], out[1]


def segments_by_centre(heights_m: tuple[float, float] | None, params: AssignmentParams = WALKING.assignment) -> str:
    """``"as_labelled"`` when the thigh sensor lies higher above the knee centre than the shank sensor, by more than
    ``centre_height_margin_m`` (:func:`centre_heights_m`), ``"swapped"`` when it lies as much lower, else
    ``"undecided"``."""
    if heights_m is None or not np.all(np.isfinite(heights_m)):
        return "undecided"
    above = heights_m[0] - heights_m[1]
    if above > params.centre_height_margin_m:
        return "as_labelled"
    return "swapped" if above < -params.centre_height_margin_m else "undecided"


def pairing_suspicious(residuals_mps2: tuple[float, float], params: AssignmentParams = WALKING.assignment) -> bool:
    """Whether the labelled thigh pairing of the two legs (their joint-centre fit residuals [m/s^2]) is worth
    testing against the swapped one."""
    return max(residuals_mps2) > params.centre_suspect_mps2


def swapped_pairing_better(labelled_mps2: tuple[float, float], swapped_mps2: tuple[float, float],
                           params: AssignmentParams = WALKING.assignment) -> bool:
    """Whether each thigh fits the other leg's shank clearly better than its own (Seel Eq. 5 residuals [m/s^2]):
    the summed residual drops below ``pairing_gain`` of the labelled one and neither leg's gets worse. Relative
    only: soft tissue and sensor filtering raise every residual on real sensors (0.64-0.65 with the right pairing
    on the biomechZoo Xsens trial, 2.1-2.7 with the thighs exchanged), so no absolute level marks a good fit."""
    return sum(swapped_mps2) < params.pairing_gain * sum(labelled_mps2) \
        and all(s < lab for s, lab in zip(swapped_mps2, labelled_mps2, strict=True))


def weight_shift_dps(gyr_thigh_rps: np.ndarray, acc_thigh_mps2: np.ndarray,
                     valid: np.ndarray, j1: np.ndarray, strides: list[tuple[int, int, int]],
                     params: AssignmentParams = WALKING.assignment) -> tuple[float, float] | None:
    """Two medians over whole strides [deg/s], positive for a left leg: the thigh's mean rotation rate about the
    walking direction over the first ``shift_window`` of each stride (heel strike on), and the same less the
    stride's own mean rate (module docstring). ``gyr_thigh_rps``, ``acc_thigh_mps2``: (N, 3) on the leg's grid,
    ``valid`` (N,); ``j1``: the oriented knee axis in the thigh frame (flexion rate ``g1.j1 - g2.j2``);
    ``strides``: ``(hs, to, hs_next)``. The walking direction is ``j1`` x the thigh's mean specific force over the
    strides: gravity at the thigh's mean orientation in gait (its acceleration averages out over whole cycles). The
    session's mean would lean towards wherever the thigh rested: in a session mostly seated (the thigh horizontal)
    it turned the walking direction towards the thigh's long axis, and an independent simulator's "sit, walk, sit"
    sessions read as swapped sides in 8 of 8.

    A small error of ``j1`` leaks the large sagittal rate into that direction with a random sign per leg: removed
    by regressing the rate on ``g1.j1`` over the strides. The stride's mean rate is no rotation of the thigh (its
    orientation is periodic) but what body-frame rates rectify: an uncorrected gyro bias, and the coning of a
    flexing thigh that also turns about its long axis (hip rotation, a skin or strap turning with the knee; its
    sense follows how the skin moves, which no one measured). Only the second figure is free of it. None with
    fewer than ``shift_min_strides`` whole strides or no vertical."""
    if len(strides) < params.shift_min_strides:
        return None
    arr = np.asarray(strides)
    in_strides = ranges_mask(valid.shape[0], arr[:, 0], arr[:, 2] + 1) & valid
    up = mean_up(acc_thigh_mps2, in_strides)
    if up is None:
        return None
    forward = np.cross(j1, up)
    forward /= np.linalg.norm(forward)
    w = np.rad2deg(gyr_thigh_rps @ forward)
    sagittal = np.rad2deg(gyr_thigh_rps @ j1)
    gait = in_strides & np.isfinite(w) & np.isfinite(sagittal)
    ss = float(np.dot(sagittal[gait], sagittal[gait]))
    if ss > 0:
        w = w - float(np.dot(w[gait], sagittal[gait])) / ss * sagittal
    ok = valid & np.isfinite(w)
    x = np.where(ok, w, 0.0)
    lo, end = arr[:, 0], arr[:, 2] + 1
    hi = lo + np.round(params.shift_window * (arr[:, 2] - lo)).astype(int) + 1
    whole = segment_sums(ok, lo, end) == end - lo
    if int(whole.sum()) < params.shift_min_strides:
        return None
    early = segment_sums(x, lo, hi)[whole] / (hi - lo)[whole]
    cycle = segment_sums(x, lo, end)[whole] / (end - lo)[whole]
    return float(np.median(early)), float(np.median(early - cycle))


def side_verdict(left: tuple[float, float] | None, right: tuple[float, float] | None,
                 params: AssignmentParams = WALKING.assignment) -> str:
    """``"as_labelled"``, ``"swapped"`` (both figures of both legs' weight shifts, :func:`weight_shift_dps`, in the
    other leg's sense by at least ``shift_min_dps``) or ``"undecided"``."""
    if left is None or right is None:
        return "undecided"
    m = params.shift_min_dps
    if min(left) >= m and max(right) <= -m:
        return "as_labelled"
    if max(left) <= -m and min(right) >= m:
        return "swapped"
    return "undecided"
