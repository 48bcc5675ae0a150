"""GO and CF estimators and per-stride metrics on analytic signals."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.estimators import available, get_estimator
from pipeline.estimators.cf import complementary_filter
from pipeline.estimators.go import integrate_runs
from pipeline.metrics import stride_values


def test_registry_names_every_builtin_and_rejects_others() -> None:
    assert available() == ["cf", "ekf", "go", "kf"]
    assert callable(get_estimator("go"))
    with pytest.raises(ValueError, match="available: cf, ekf, go, kf"):
        get_estimator("nope")


def test_cf_is_eq17_recursion() -> None:
    """Seel Eq. 17 written as a loop equals the vectorised lfilter form."""
    rng = np.random.default_rng(0)
    fs = 100.0
    n = 500
    rate = 50 * np.sin(np.arange(n) / 20) + rng.standard_normal(n)
    acc = 10 + 5 * rng.standard_normal(n)
    out = complementary_filter(rate, acc, fs, np.ones(n, dtype=bool), tau_s=0.5)
    lam = (1 / fs) / 0.5
    y = float(np.median(acc[:100] - np.cumsum(rate[:100]) / fs))
    ref = []
    for k in range(n):
        y = lam * acc[k] + (1 - lam) * (y + rate[k] / fs)
        ref.append(y)
    np.testing.assert_allclose(out, ref, atol=1e-9)


def test_cf_started_during_gait_starts_at_the_knee_angle() -> None:
    """A run that starts mid-stride (after a gap) starts at the angle, not at the median of a second of gait."""
    fs = 100.0
    t = np.arange(0, 3, 1 / fs)
    truth = 30 + 30 * np.sin(2 * np.pi * t / 1.1 + 2.0)
    rate = np.gradient(truth, 1 / fs)
    acc = truth + np.random.default_rng(1).normal(0, 3, t.size)
    out = complementary_filter(rate, acc, fs, np.ones(t.size, dtype=bool), tau_s=0.5)
    assert abs(out[0] - truth[0]) < 2.0
    assert np.max(np.abs(out - truth)) < 3.0


def test_cf_converges_to_the_accelerometer_level_despite_gyro_bias() -> None:
    fs = 100.0
    t = np.arange(0, 30, 1 / fs)
    true = 20 + 30 * np.sin(2 * np.pi * t)
    rate = np.gradient(true, 1 / fs) + 5.0  # 5 deg/s gyro bias
    acc = true + np.random.default_rng(1).normal(0, 3, t.size)
    out = complementary_filter(rate, acc, fs, np.ones(t.size, dtype=bool), tau_s=1.0)
    # steady-state error of a first-order CF under a rate bias is bias * tau = 5 deg
    assert abs(np.mean(out[-1000:] - true[-1000:]) - 5.0) < 1.0


def test_integration_restarts_on_each_valid_run() -> None:
    valid = np.ones(300, dtype=bool)
    valid[100:120] = False
    out = integrate_runs(np.full(300, 100.0), 100.0, valid)
    assert np.isnan(out[100:120]).all()
    assert out[0] == 0 and out[120] == 0
    assert out[99] == 99.0  # 100 deg/s for 0.99 s


def test_stride_metrics_on_a_known_curve() -> None:
    fs = 100.0
    t = np.arange(0, 1.2, 1 / fs)
    angle = 10 + 25 * np.exp(-0.5 * ((t - 0.85) / 0.1) ** 2) + 8 * np.exp(-0.5 * ((t - 0.15) / 0.05) ** 2)
    v = stride_values(angle, t, 0, 70, 119)
    assert abs(v.stance_pct - 100 * 0.70 / 1.19) < 1e-9
    assert abs(v.peak_swing_flexion_deg - 35.0) < 0.1
    assert abs(v.stance_flexion_deg - 18.0) < 0.2
    assert abs(v.min_flexion_deg - 10.0) < 0.1
    assert abs(v.rom_deg - 25.0) < 0.2
    assert abs(v.duration_s - 1.19) < 1e-9 and abs(v.swing_time_s - 0.49) < 1e-9
