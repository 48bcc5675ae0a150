"""Complementary filter of Seel et al. 2014 (Rhudy et al. 2024, Eq. 17): the gyroscope angle increment (Eq. 4)
corrected towards the accelerometer angle (Eq. 6-7) with a fixed gain lambda."""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from pipeline.estimators import LegData, register
from pipeline.signal_utils import true_runs

# Time constant of the accelerometer correction: lambda = dt / TAU_S (Eq. 17) keeps the filter rate-independent.
# 0.5 s: shorter follows accelerometer noise on real data (biomechZoo), longer lets gyro bias through (simulator).
TAU_S = 0.5


def complementary_filter(rate_dps: np.ndarray, acc_angle_deg: np.ndarray, fs_hz: float,
                         valid: np.ndarray, tau_s: float = TAU_S) -> np.ndarray:
    """Eq. 17, ``a[n] = lam*acc[n] + (1-lam)*(a[n-1] + rate[n]*dt)``, as a first-order IIR (``lfilter``) run
    separately on each valid run and started at the run's first second of accelerometer angle (median)."""
    dt = 1.0 / fs_hz
    lam = min(dt / tau_s, 1.0)
    out = np.full(rate_dps.shape[0], np.nan)
    for a, b in true_runs(valid & np.isfinite(rate_dps) & np.isfinite(acc_angle_deg)):
        u = lam * acc_angle_deg[a:b] + (1.0 - lam) * rate_dps[a:b] * dt
        y0 = float(np.median(acc_angle_deg[a:min(b, a + int(fs_hz))]))
        y, _ = lfilter([1.0], [1.0, -(1.0 - lam)], u, zi=np.array([(1.0 - lam) * y0]))
        out[a:b] = y
    return out


@register("cf")
def cf_estimator(data: LegData) -> np.ndarray:
    """Eq. 17. Walking: the accelerometer angle zeroed on quiet standing, as Allseits et al. 2018 (Sect. 2.4.2) did
    for their CF comparison (:func:`pipeline.fusion.standing_reference`); without standing the offset of the
    joint-plane frames stays in."""
    if data.activity == "running":  # impact-free updates and the KF's inputs (pipeline.running)
        from pipeline.estimators.kf import cf_running_leg

        return cf_running_leg(data)
    from pipeline.fusion import STANDING_KNEE_DEG, in_bouts, standing_reference

    angle = complementary_filter(data.rate_dps, data.acc_angle_deg, data.fs_hz, data.prep.valid)
    ref = standing_reference(data, data.acc_angle_deg, in_bouts(data))
    data.extras["cf_standing_ref_deg"] = ref
    return angle if ref is None else angle - (ref - STANDING_KNEE_DEG)
