"""Complementary filter of Seel et al. 2014 (Rhudy et al. 2024, Eq. 17): the gyroscope angle increment (Eq. 4)
corrected towards the accelerometer angle (Eq. 6-7) with a fixed gain lambda = dt / tau, which keeps the filter
independent of the sampling rate."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from pipeline.estimators.kf import (
    FilterDiagnostics,
    filter_setup,
    gain_for_time_constant,
    interval_rate,
    linear_recursion,
    start_from_measurement,
)
from pipeline.filter_inputs import debiased_rate, run_per_segment, update_mask
from pipeline.leg_input import EstimatorDiagnostics, LegInput
from pipeline.params import WALKING
from pipeline.posture import in_bouts, leg_quiet, standing_reference
from pipeline.signal_utils import segment_sums, true_runs


@dataclass(frozen=True, kw_only=True)
class CfDiagnostics(EstimatorDiagnostics):
    """Walking CF: the standing reading it was zeroed on (``standing_ref_deg``, None when not zeroed)."""


def complementary_filter(rate_dps: np.ndarray, acc_angle_deg: np.ndarray, fs_hz: float,
                         valid: np.ndarray, tau_s: float = WALKING.cf.tau_s) -> np.ndarray:
    """Eq. 17, ``a[n] = lam*acc[n] + (1-lam)*(a[n-1] + rate[n]*dt)``, as a first-order IIR (``lfilter``) run
    separately on each valid run. Each run starts at the angle that best explains its first second of accelerometer
    angle given the gyroscope's motion (median of accelerometer angle minus the rate's integral): during gait the
    knee moves 60 deg within that second, so the accelerometer angle's own median is no start value, while the
    integral's drift over one second is well below a degree (gyro bias ~1 deg/s).
    Arrays (N,): rate [deg/s], accelerometer angle [deg], valid; returns the angle (N,) [deg], NaN elsewhere."""
    dt = 1.0 / fs_hz
    lam = min(dt / tau_s, 1.0)
    out = np.full(rate_dps.shape[0], np.nan)
    for a, b in true_runs(valid & np.isfinite(rate_dps) & np.isfinite(acc_angle_deg)):
        u = lam * acc_angle_deg[a:b] + (1.0 - lam) * rate_dps[a:b] * dt
        m = min(b, a + max(int(fs_hz), 1))
        moved = np.cumsum(rate_dps[a:m]) * dt  # the gyroscope's angle change from the start, as Eq. 17 adds it
        y0 = float(np.median(acc_angle_deg[a:m] - moved))
        y, _ = lfilter([1.0], [1.0, -(1.0 - lam)], u, zi=np.array([(1.0 - lam) * y0]))
        out[a:b] = y
    return out


def walking_cf(leg: LegInput) -> np.ndarray:
    """Eq. 17 on a walking leg (:func:`complementary_filter`), restarted after a hole filled from the neighbouring
    strides where the leg is quiet for most of the second after it (``CfParams.restart_quiet_share``;
    :func:`pipeline.filter_inputs.run_per_segment`). A fill is a neighbouring stride's motion: where the gait did
    not go on as before (the hole over a bout's last step) its integral is tens of degrees off, and a filter
    carrying it shows the standing after it that far off for a time constant or more. Quiet, the accelerometer
    angle sees gravity only, so the restart starts right. Within gait a fill is near the truth and a restart would
    start from the accelerometer angle in motion, a few degrees off (10 % bursty loss, report seeds: peak LoA
    -4.1 .. 5.0 deg carried, -5.0 .. 5.9 restarted): it carries on. Returns (N,) [deg] with the accelerometer
    angle's own zero (not yet zeroed on standing)."""
    rate, acc, valid = leg.rate_dps, leg.acc_angle_deg, leg.prep.valid
    fs, tau = leg.fs_hz, leg.params.cf.tau_s
    second = max(int(fs), 1)
    starts = np.arange(valid.shape[0])
    quiet_after = segment_sums(leg_quiet(leg), starts, np.minimum(starts + second, valid.shape[0]))
    mostly_quiet = quiet_after >= leg.params.cf.restart_quiet_share * second
    return run_per_segment(leg, lambda a, b: complementary_filter(rate[a:b], acc[a:b], fs, valid[a:b], tau),
                           valid & np.isfinite(acc), restart_ok=mostly_quiet)


def cf_running_leg(leg: LegInput, tau_s: float | None = None) -> tuple[np.ndarray, FilterDiagnostics]:
    """Eq. 17 (constant gain ``lambda = dt / tau``) on a running leg, with the same inputs as the KF (de-biased
    rate, standing zero, measurement updates only where :func:`pipeline.filter_inputs.update_mask` allows: Rhudy et
    al. skip the impacts for CF, KF and EKF alike) and the same time constant, so the two differ only in the gain
    schedule."""
    tau, diag, _ = filter_setup(leg, tau_s)
    raw_rate = debiased_rate(leg)
    rate = interval_rate(raw_rate)
    mask = update_mask(leg)
    z = np.asarray(leg.acc_angle_deg, dtype=float) - diag.acc_zero_deg
    fs = leg.fs_hz
    lam = gain_for_time_constant(tau, fs)

    def run(a: int, b: int) -> np.ndarray:
        gains = np.where(mask[a:b], lam, 0.0)
        drive = np.concatenate(([0.0], rate[a:b - 1] / fs))
        x0 = start_from_measurement(z[a:b], mask[a:b], raw_rate[a:b], 1.0 / fs)
        return linear_recursion(1.0 - gains, (1.0 - gains) * drive + gains * np.where(mask[a:b], z[a:b], 0.0), x0)

    return run_per_segment(leg, run, mask), diag


def cf_estimator(leg: LegInput) -> tuple[np.ndarray, EstimatorDiagnostics]:
    """Eq. 17. Walking: the accelerometer angle zeroed on quiet standing, as Allseits et al. 2018 (Sect. 2.4.2) did
    for their CF comparison (:func:`pipeline.posture.standing_reference`); without standing the offset of the
    joint-plane frames stays in. Running: impact-free updates and the KF's inputs (:func:`cf_running_leg`)."""
    if leg.activity == "running":
        return cf_running_leg(leg)
    angle = walking_cf(leg)
    ref = standing_reference(leg, leg.acc_angle_deg, in_bouts(leg))
    diag = CfDiagnostics(standing_ref_deg=ref)
    return (angle if ref is None else angle - (ref - leg.params.posture.standing_knee_deg)), diag
