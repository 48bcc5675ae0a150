"""Automatic tuning of the gyro/accelerometer blend of the KF and EKF without motion capture.

Rhudy et al. 2024 tuned Q (R = 1) per dataset against Vicon (Fig. 10) and suggest for practice (Sect. 4): increase
the process noise until the gyroscope drift of the estimated knee angle is corrected, no further (beyond that the
estimate follows the accelerometer angle and its errors). Here the drift that remains after the per-stride de-biasing
(:func:`pipeline.estimators.kf.stride_bias_dps`) is measured directly, so no trial filtering is needed:

* every stride's closure rate ``integral(rate) / duration`` (the knee returns to its angle, so this is the bias of
  that stride plus the true stride-to-stride change) scatters with a robust SD ``s``;
* the smoothed bias averages ``SMOOTH_STRIDES`` of them, so its error is about ``1.25 s / sqrt(SMOOTH_STRIDES)``
  (deg/s): the drift rate the filter has to correct;
* the fusion time constant is the longest for which that drift stays within ``DRIFT_TOL_DEG``:
  ``tau = DRIFT_TOL_DEG / drift_rate``, within ``TAU_RANGE_S``.

The smallest process noise that still corrects the drift, as the paper suggests, without a reference. Why not
"raise Q until the per-stride peaks/minima stop trending" literally: it was tried (bench/accuracy.py, running
pattern) and failed in the way one should expect: the accelerometer angle in motion carries a systematic level error
of several degrees (lever-arm correction from estimated joint centres), and a trend between a quiet-standing anchor and
that level looks like drift, so the rule pushed Q up, towards the biased level (mean RMSE 3.7 vs 2.8 deg).
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.estimators import LegData

DRIFT_TOL_DEG = 2.0
TAU_RANGE_S = (0.5, 16.0)
SMOOTH_STRIDES = 15
MIN_STRIDES = 6
DEFAULT_TAU_S = 4.0


def closure_rates_dps(rate_dps: np.ndarray, strides: list[tuple[int, int]]) -> np.ndarray:
    """``integral(rate) / duration`` of every fully valid stride (deg/s)."""
    out = []
    for a, b in strides:
        r = rate_dps[a:b + 1]
        if b - a >= 2 and np.isfinite(r).all():
            out.append(float(np.trapezoid(r) / (b - a)))
    return np.asarray(out)


def tune_time_constant(data: LegData, rate_dps: np.ndarray | None = None) -> tuple[float, dict]:
    """Fusion time constant (s) for the leg's KF/EKF from the gyroscope's residual drift, and JSON-serialisable
    diagnostics. ``rate_dps``: the knee rate (default ``data.rate_dps``; de-biasing does not change the scatter)."""
    from pipeline.estimators.kf import leg_strides

    strides = leg_strides(data)
    rates = closure_rates_dps(data.rate_dps if rate_dps is None else rate_dps, strides)
    if rates.size < MIN_STRIDES:
        return DEFAULT_TAU_S, {"tau_s": DEFAULT_TAU_S, "reason": "too few strides"}
    med = float(np.median(rates))
    sd = 1.4826 * float(np.median(np.abs(rates - med)))
    drift = max(1.2533 * sd / math.sqrt(min(SMOOTH_STRIDES, rates.size)), 1e-6)
    tau = float(np.clip(DRIFT_TOL_DEG / drift, *TAU_RANGE_S))
    return tau, {"tau_s": round(tau, 2), "residual_drift_dps": round(drift, 3), "strides": int(rates.size)}
