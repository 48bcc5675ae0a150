"""Automatic tuning of the gyro/accelerometer blend of the KF and EKF without motion capture.

Rhudy et al. 2024 tuned Q (R = 1) per dataset against Vicon (Fig. 10) and suggest for practice (Sect. 4): increase
the process noise until the gyroscope drift of the estimated knee angle is corrected, no further (beyond that the
estimate follows the accelerometer angle and its errors). Here the drift that remains after the per-stride de-biasing
(:func:`pipeline.filter_inputs.stride_bias_dps`) is measured directly, so no trial filtering is needed:

* every stride's closure rate ``integral(rate) / duration`` (the knee returns to its angle, so this is the bias of
  that stride plus the true stride-to-stride change) scatters with a robust SD ``s``;
* the smoothed bias averages ``n = FilterInputParams.bias_smooth_strides`` of them, so its error is about
  ``1.25 s / sqrt(n)`` (deg/s): the drift rate the filter has to correct;
* the fusion time constant is the longest for which that drift stays within ``TuningParams.drift_tol_deg``:
  ``tau = drift_tol_deg / drift_rate``, within ``TuningParams.tau_range_s``.

The smallest process noise that still corrects the drift, as the paper suggests, without a reference. Why not
"raise Q until the per-stride peaks/minima stop trending" literally: on the running pattern of bench/accuracy.py it
fails in the way one should expect: the accelerometer angle in motion carries a systematic level error
of several degrees (lever-arm correction from estimated joint centres), and a trend between a quiet-standing anchor and
that level looks like drift, so the rule pushes Q up, towards the biased level (mean RMSE 3.7 vs 2.8 deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.leg_input import LegInput


@dataclass(frozen=True)
class TuningDiagnostics:
    """The tuned fusion time constant and what it came from."""

    tau_s: float
    residual_drift_dps: float | None = None  # drift rate the filter has to correct; None when not tuned
    strides: int = 0  # fully valid strides the scatter was measured on
    reason: str | None = None  # why the untuned constant was used


def closure_rates_dps(rate_dps: np.ndarray, strides: list[tuple[int, int]]) -> np.ndarray:
    """``integral(rate) / duration`` [deg/s] of every fully valid stride ``(start, stop)`` of ``rate_dps`` (N,)."""
    out = []
    for a, b in strides:
        r = rate_dps[a:b + 1]
        if b - a >= 2 and np.isfinite(r).all():
            out.append(float(np.trapezoid(r) / (b - a)))
    return np.asarray(out)


def tune_time_constant(leg: LegInput, rate_dps: np.ndarray | None = None) -> tuple[float, TuningDiagnostics]:
    """Fusion time constant [s] for the leg's KF/EKF from the gyroscope's residual drift, and its diagnostics.
    ``rate_dps`` (N,): the knee rate (default ``leg.rate_dps``; de-biasing does not change the scatter)."""
    p = leg.params.tuning
    rates = closure_rates_dps(leg.rate_dps if rate_dps is None else rate_dps, leg.filter_strides)
    if rates.size < p.min_strides:
        return p.untuned_tau_s, TuningDiagnostics(tau_s=p.untuned_tau_s, strides=int(rates.size),
                                                  reason="too few strides")
    med = float(np.median(rates))
    sd = 1.4826 * float(np.median(np.abs(rates - med)))
    drift = max(1.2533 * sd / math.sqrt(min(leg.params.filter_inputs.bias_smooth_strides, rates.size)), 1e-6)
    tau = float(np.clip(p.drift_tol_deg / drift, *p.tau_range_s))
    return tau, TuningDiagnostics(tau_s=round(tau, 2), residual_drift_dps=round(drift, 3), strides=int(rates.size))
