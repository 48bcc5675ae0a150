"""What every estimator and policy reads about one leg: a frozen value built once per leg by :mod:`pipeline.walking`
or :mod:`pipeline.running`, and the estimator interface.

An estimator is a function ``(LegInput) -> (angle_deg, diagnostics)``: knee flexion (N,) [deg] on the leg's grid,
NaN where it has no estimate, and a frozen :class:`EstimatorDiagnostics` (or a subclass).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from pipeline.axes import JointAxes, JointCentres
from pipeline.params import PipelineParams
from pipeline.phases import GaitEvents
from pipeline.prepare import PreparedLeg


@dataclass(frozen=True)
class LegInput:
    """One prepared leg with its axes, rates, events and accelerometer angle (arrays (N,) on ``prep``'s grid)."""

    prep: PreparedLeg  # running: already through the 7 Hz low-pass (``prefiltered``)
    axes: JointAxes
    centres: JointCentres
    rate_dps: np.ndarray  # knee flexion rate g1.j1 - g2.j2 (Seel Eq. 4 integrand), NaN where masked
    acc_angle_deg: np.ndarray  # accelerometer knee angle (Seel Eq. 6-7), NaN where masked
    shank_sag_dps: np.ndarray  # g2.j2, positive mid-swing
    events: GaitEvents
    params: PipelineParams
    activity: Literal["walking", "running"] = "walking"
    running_cycles: tuple[tuple[int, int], ...] | None = None  # foot strike -> next foot strike (running)
    acc_update_mask: np.ndarray | None = None  # further restricts accelerometer updates (running: impact-free)
    quiet_mask: np.ndarray | None = None  # precomputed :func:`pipeline.posture.quiet_mask` (running)
    prefiltered: bool = False  # ``prep``'s signals are already low-passed: the filters must not filter again
    # running: the leg before that low-pass (the cycle-mean gravity integrates the gyro through the swing, whose
    # rates reach 600-1000 deg/s with content up to ~20 Hz; pipeline.cycle_gravity)
    unfiltered: PreparedLeg | None = None

    @property
    def fs_hz(self) -> float:
        """Sampling rate of the leg's grid [Hz]."""
        return self.prep.fs_hz

    @property
    def thigh_sag_dps(self) -> np.ndarray:
        """The thigh's sagittal rate g1.j1 [deg/s] (N,), forward positive, NaN where masked: the knee rate plus the
        shank's."""
        return self.rate_dps + self.shank_sag_dps

    @property
    def filter_strides(self) -> list[tuple[int, int]]:
        """Stride intervals ``(start, stop)`` for de-biasing and tuning: running's foot-strike cycles when there
        are any, else the gait-event strides."""
        if self.running_cycles:
            return [(int(a), int(b)) for a, b in self.running_cycles]
        return [(a, b) for a, _, b in self.events.strides]


@dataclass(frozen=True, kw_only=True)
class EstimatorDiagnostics:
    """What every estimator reports: the accelerometer angle of quiet upright standing that anchored its level
    (None when nothing did)."""

    standing_ref_deg: float | None = None


Estimator = Callable[[LegInput], tuple[np.ndarray, EstimatorDiagnostics]]
