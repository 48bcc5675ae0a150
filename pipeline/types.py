"""Data types at the boundary between the pipeline and its callers (server, bench, simulator).

Units are part of the names: ``t_s`` seconds, ``angle_deg`` degrees, ``fs_hz`` hertz.
Raw streams carry their declared units as strings; :mod:`pipeline.prepare` converts them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Literal

import numpy as np

Leg = Literal["left", "right"]
Segment = Literal["thigh", "shank"]
GyroUnit = Literal["deg/s", "rad/s"]
AccUnit = Literal["m/s2", "g"]
Activity = Literal["walking", "running", "unknown"]


@dataclass(frozen=True)
class RawSensorStream:
    """All samples of one IMU in one session, as uploaded (any order is sorted by the caller).

    ``t_s`` is seconds since the session started on the app's clock, strictly increasing.
    ``gyr`` and ``acc`` are (N, 3) in the units named by ``gyro_unit`` and ``acc_unit``.
    """

    sensor_id: str
    leg: Leg
    segment: Segment
    fs_hz: float
    t_s: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    gyro_unit: GyroUnit = "deg/s"
    acc_unit: AccUnit = "m/s2"


@dataclass(frozen=True)
class StrideValues:
    """Timing and angles of one stride: heel strike to the next heel strike of the same leg."""

    t_start_s: float
    t_end_s: float
    duration_s: float
    t_toe_off_s: float
    stance_time_s: float
    swing_time_s: float
    stance_pct: float
    peak_swing_flexion_deg: float
    min_flexion_deg: float
    rom_deg: float
    stance_flexion_deg: float


@dataclass(frozen=True, kw_only=True)
class StrideMetrics(StrideValues):
    """One stride's values with its leg, position and the estimator that produced its angle."""

    leg: Leg
    index: int
    estimator: str
    quality: float  # 0 (untrustworthy) .. 1 (all checks passed)
    quality_reasons: tuple[str, ...] = ()
    # the activity the stride's leg was processed as ("walking" or "running"; never "unknown")
    activity: str = "walking"
    # True when the policy's primary estimator for that activity failed on this stride and another one was used
    fallback: bool = False


class AbsoluteReference(StrEnum):
    """What anchored a leg's absolute knee angle level."""

    STANDING = "standing"  # a quiet upright standing period set the accelerometer angle's zero
    NONE = "none"  # no standing found: the level is GO's own zero (straight knee before swing) or the frames' own


@dataclass(frozen=True)
class RunningDiagnostics:
    """Foot-strike cycles and impact masking of a leg processed as running (Rhudy et al. 2024, Sect. 2.2.2)."""

    foot_strikes: int
    cycles: int
    stride_s: float | None  # median gait cycle [s], None without cycles
    impact_g: float  # median high-frequency amplitude of the foot strikes [g]
    impact_masked_pct: float  # share of samples within +-5 % of the cycle around a strike [%]
    acc_update_pct: float  # share of samples where the accelerometer may update the filters [%]


@dataclass(frozen=True)
class KneeCalibration:
    """A clinician's statement of one leg's knee flexion in quiet upright standing (goniometer reading or a guided
    stand-still trial). It replaces the assumed standing flexion as the absolute zero of that leg's angles: a
    post-surgery knee may stand in 5-15 deg of flexion contracture, which no IMU-only method can see."""

    standing_knee_deg: float
    method: str = "goniometer"  # how it was measured: "goniometer" or "guided_trial"
    calibration_id: str | None = None  # the caller's identifier, echoed in the leg's diagnostics


TRACE_WITHHELD_NO_GAIT = "no_gait"
"""``LegDiagnostics.trace_withheld``: the leg has no gait stride to learn its knee axes and zero from."""


@dataclass(frozen=True)
class MountingCheck:
    """:func:`pipeline.mounting.check_mounting`: the largest change of each segment's knee axis [deg] between the
    time windows before and after one point in time, and :func:`pipeline.mounting.level_step`: that of the level."""

    thigh_deg: float | None  # None: too few windows to judge
    shank_deg: float | None
    at_s: float | None  # the split point of the check that found the change (else the axes') [s]
    windows: int  # windows that moved enough to be fitted
    changed: bool  # beyond MountingParams.thigh_deg or shank_deg, or a level step beyond level_step_deg
    level_step_deg: float | None = None  # the largest step of the level seen alike standing and walking; None: unjudged


@dataclass(frozen=True)
class LegDiagnostics:
    """How one leg was processed: fit residuals, clock correction, absolute reference, stride counts.
    JSON-serialisable through :func:`dataclasses.asdict` (the enum is a ``str``)."""

    activity: str  # "walking" or "running": what the leg was processed as
    axis_rms_residual_dps: float  # Seel Eq. 2 fit residual
    axis_fit_samples: int
    centre_rms_residual_mps2: float  # Seel Eq. 5 fit residual
    shank_lag_ms: float | None  # shank clock offset at mid-session; None when no correction was applied
    shank_drift_ppm: float | None  # shank clock rate error; None when no correction was applied
    absolute_reference: AbsoluteReference
    standing_ref_deg: float | None  # accelerometer angle of quiet upright standing, None without
    bouts: int
    bridged_gaps: int
    n_strides: int
    n_fallback: int  # strides where the activity's primary estimator was replaced
    j1: tuple[float, ...]  # knee axis, thigh frame
    j2: tuple[float, ...]  # knee axis, shank frame
    o1_m: tuple[float, ...]  # thigh sensor relative to the knee centre [m]
    o2_m: tuple[float, ...]  # shank sensor relative to the knee centre [m]
    cf_shift_deg: float | None = None  # walking auto: shift applied to the CF fallback
    offset_median_deg: float | None = None  # walking auto: median per-stride offset of GO to the accelerometer
    # the level the gyros carry from quiet standing (pipeline.quiet_bridge) minus the accelerometer's level in motion
    # [deg], median over strides (None without both); ``level_bridged``: they disagreed beyond
    # FusionParams.bridge_disagree_deg (running: RunningParams.bridge_disagree_deg) and the leg took the bridged level
    bridge_check_deg: float | None = None
    level_bridged: bool = False
    fallback_bridge_check_deg: float | None = None  # the check on the CF fallback strides alone (walking auto)
    # running auto: the median shift [deg] that moved the filter's curve to the level of the cycle-mean gravity
    # (pipeline.cycle_gravity); None where no such level was found (no standing, too few whole cycles)
    gravity_shift_deg: float | None = None
    tau_s: float | None = None  # KF/EKF fusion time constant when tuned
    running: RunningDiagnostics | None = None
    # the standing knee flexion the level rests on, and whether it was measured ("calibration") or "assumed"
    standing_knee_deg: float | None = None
    level_source: str = "assumed"
    calibration_id: str | None = None
    # knee angles outside the plausibility band (pipeline.params.PostureParams.plausible_knee_deg), masked to NaN
    masked_implausible_samples: int = 0
    # what the sensor-label checks did (pipeline.assignment): "as_labelled", "thigh_shank_exchanged" or
    # "thighs_exchanged_between_legs"
    assignment: str = "as_labelled"
    # each sensor's accelerometer offset [m/s^2] and gyro bias [deg/s] (sensor frames) as the session's rests showed
    # them, removed before processing (pipeline.rest_offset); zeros without rests
    acc_offset_thigh_mps2: tuple[float, ...] = (0.0, 0.0, 0.0)
    acc_offset_shank_mps2: tuple[float, ...] = (0.0, 0.0, 0.0)
    gyr_bias_thigh_dps: tuple[float, ...] = (0.0, 0.0, 0.0)
    gyr_bias_shank_dps: tuple[float, ...] = (0.0, 0.0, 0.0)
    # how far Seel's hinge axes leaned out of the level (thigh, shank) [deg]; beyond AxesParams.level_lean_deg the
    # knee axes were levelled and the clock taken from the joint centre (a knee that turns as it flexes)
    hinge_lean_deg: tuple[float, ...] | None = None
    knee_axes_levelled: bool = False
    # the thigh's and shank's clocks run apart faster than crystal clocks can, as the clock windows
    # (pipeline.sync.ClockFit; then no correction was applied) or the stride timing (pipeline.sync.
    # stride_clock_runaway; after any correction) show: every stride flagged ``clock_disagreement``
    clock_disagreement: bool = False
    # the thigh's weight-shift rotation in early stance [deg/s], as measured and less the stride's mean rate,
    # positive on a left leg (pipeline.assignment.weight_shift_dps); None for running legs or too few strides
    weight_shift_dps: tuple[float, float] | None = None
    # why the leg's knee-angle trace was withheld (every sample NaN; chunked sessions: in every chunk), None when it
    # was not: TRACE_WITHHELD_NO_GAIT
    trace_withheld: str | None = None
    # strides the gait events delimit that the other leg's swings do not contradict (pipeline.bilateral.gait_strides;
    # running: foot-strike cycles) and that are steps (pipeline.stepping), before any other per-stride check
    gait_strides: int = 0
    # how far the thigh and the shank sensor lie above the knee centre [m] (pipeline.assignment.centre_heights_m)
    centre_heights_m: tuple[float, float] | None = None
    # strides dropped because the thigh neither turned forward through their swing nor landed forward of its push-off:
    # a lifted leg lowered in place (as in marching) or a side step, no step forward (pipeline.stepping)
    lowered_strides: int = 0
    # the mounting-change check (pipeline.mounting.MountingCheck); None where it did not run
    mounting: MountingCheck | None = None
    # time spans [s] in which the leg's sensors were not on the leg (pipeline.worn): nothing estimated there
    not_worn_s: tuple[tuple[float, float], ...] = ()
    # those of them in which the sensors were handled: the leg was processed apart on either side
    handled_s: tuple[tuple[float, float], ...] = ()


@dataclass
class LegResult:
    """The continuous knee flexion estimate and the strides of one leg."""

    leg: Leg
    fs_hz: float
    t_s: np.ndarray  # common time grid of the leg, seconds since session start
    angle_deg: np.ndarray  # knee flexion, positive = flexion, NaN inside gaps
    estimator: np.ndarray  # per-sample estimator name (str array), "" where no estimate
    strides: list[StrideMetrics]
    gaps_s: list[tuple[float, float]] = field(default_factory=list)
    walking_s: float = 0.0
    activity: str = "walking"  # what the leg was processed as: "walking" or "running"
    diagnostics: LegDiagnostics | None = None  # None only for results not made by the pipeline (test doubles)

    def without(self, drop: set[int]) -> LegResult:
        """This leg without the strides at the indices ``drop``, the rest renumbered and its counts updated."""
        kept = [dataclasses.replace(s, index=i) for i, s in enumerate(x for k, x in enumerate(self.strides)
                                                                        if k not in drop)]
        diag = self.diagnostics
        if diag is not None:
            diag = dataclasses.replace(diag, n_strides=len(kept), n_fallback=sum(1 for s in kept if s.fallback))
        return dataclasses.replace(self, strides=kept, walking_s=float(sum(s.duration_s for s in kept)),
                                   diagnostics=diag)


@dataclass
class SessionResult:
    """The result of :func:`pipeline.session.process_session`: per-leg results and session warnings."""

    algorithm_version: str
    activity: str
    legs: dict[str, LegResult]
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        """A small JSON-serialisable summary per leg (stored with the session)."""
        out: dict = {"algorithm_version": self.algorithm_version, "activity": self.activity,
                     "warnings": list(self.warnings), "legs": {}}
        for leg, res in self.legs.items():
            strides = res.strides
            peaks = [s.peak_swing_flexion_deg for s in strides]
            roms = [s.rom_deg for s in strides]
            out["legs"][leg] = {
                "n_strides": len(strides),
                "walking_s": round(float(res.walking_s), 2),
                "peak_swing_flexion_deg_median": float(np.median(peaks)) if peaks else None,
                "rom_deg_median": float(np.median(roms)) if roms else None,
                "estimators": {e: sum(1 for s in strides if s.estimator == e)
                               for e in sorted({s.estimator for s in strides})},
                "gaps": len(res.gaps_s),
                "diagnostics": None if res.diagnostics is None else dataclasses.asdict(res.diagnostics),
            }
        return out
