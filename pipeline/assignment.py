"""Sensor-label checks: is the "thigh" sensor on the thigh, and is each thigh paired with its own leg's shank?

Thigh and shank swapped within a leg: in gait the shank swings faster than the thigh (sagittal swing peaks ~350 vs
~150 deg/s: the shank's rotation is the thigh's plus the knee's, Winter 2009, Ch. 4). The shank over thigh swing-rate
ratio is 1.9-2.7 with the right labels (simulator axes; 2.4 on the real biomechZoo Xsens trial) and 0.3-0.45 with
swapped ones, so the swap is detected and corrected by exchanging the two streams. The heel-strike impact would seem
a second witness (the shank takes it first; Lafortune 1991) and it is on the simulator, but on the real Xsens trial
the thigh's specific force changes faster than the shank's (ratio 0.64-0.68: soft tissue and sensor filtering), so
it is reported, never decisive.

Thighs swapped between the legs: each knee is a hinge about a fixed centre, so the two sensors of one leg satisfy the
rigid-body constraint of Seel et al. 2014 Eq. 5 (same knee-centre acceleration seen from both segments); a thigh of
the other leg does not (its centre residual is 3-6x larger). When a leg's residual is suspicious, the swapped pairing
is fitted too and taken when clearly better (:func:`swapped_pairing_better`).

Legs swapped (all four sensors): one leg's two IMUs are the same whichever side they are on (the mounting is
arbitrary and the knee bends the same way), so nothing in the signals tells left from right: the app must confirm the
side when the sensors are put on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.params import WALKING, AssignmentParams
from pipeline.prepare import SI, to_si
from pipeline.signal_utils import row_norm
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
        rate, impact = r2 / r1, i2 / i1
    if not np.isfinite(rate):
        return SegmentCheck(float(rate), float(impact), "undecided")
    if rate < params.swap_ratio:
        verdict = "swapped"
    elif rate > params.keep_ratio:
        verdict = "as_labelled"
    else:
        verdict = "undecided"
    return SegmentCheck(round(float(rate), 3), round(float(impact), 3), verdict)


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
