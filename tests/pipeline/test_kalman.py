"""KF (Rhudy et al. 2024 Eq. 18-21) and EKF (Eq. 22-24) on synthetic signals with a known angle."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.estimators import available
from pipeline.estimators.ekf import ekf_angle
from pipeline.estimators.kf import (
    kf_angle,
    kf_angle_loop,
    kf_gains,
    linear_recursion,
    q_for_time_constant,
    start_from_measurement,
    time_constant_for_q,
)
from pipeline.filter_inputs import run_per_segment, stride_bias_dps

FS = 200.0


def _knee(n: int, fs: float = FS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A running-like knee angle (deg), its exact rate (deg/s) and the time axis."""
    t = np.arange(n) / fs
    w = 2 * np.pi * 1.4
    angle = 55 - 40 * np.cos(w * t) + 8 * np.sin(2 * w * t)
    rate = 40 * w * np.sin(w * t) + 16 * w * np.cos(2 * w * t)
    return t, angle, rate


def _rotate(v: np.ndarray, ang_deg: np.ndarray) -> np.ndarray:
    th = np.radians(ang_deg)
    c, s = np.cos(th), np.sin(th)
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])


def test_linear_recursion_matches_loop() -> None:
    rng = np.random.default_rng(1)
    n = 5000
    a = rng.uniform(0.5, 1.0, n)
    a[rng.random(n) < 0.3] = 1.0
    b = rng.normal(0, 1, n)
    x, ref = 3.0, np.empty(n)
    for k in range(n):
        x = a[k] * x + b[k]
        ref[k] = x
    np.testing.assert_allclose(linear_recursion(a, b, 3.0), ref, rtol=1e-9, atol=1e-9)


def test_gain_closed_form_matches_riccati_loop() -> None:
    mask = np.ones(3000, dtype=bool)
    mask[100:180] = False
    mask[900:905] = False
    mask[2990:] = False
    q, r, p0 = 1e-3, 1.0, 4.0
    gains = kf_gains(mask, q, r, p0)
    p, ref = p0, np.zeros(mask.size)
    for k in range(mask.size):
        if k > 0:
            p += q
        if mask[k]:
            ref[k] = p / (p + r)
            p *= 1 - ref[k]
    np.testing.assert_allclose(gains, ref, rtol=1e-10, atol=1e-14)


def test_time_varying_r_matches_literal_equations() -> None:
    rng = np.random.default_rng(6)
    n = 4000
    _, angle, rate = _knee(n)
    z = angle + rng.normal(0, 5, n)
    scale = np.where((np.arange(n) // 700) % 2 == 0, 0.01, 1.0)  # alternating quiet and dynamic stretches
    mask = (np.arange(n) % 140) > 14
    fast = kf_angle(rate, z, FS, tau_s=2.0, update_mask=mask, r_scale=scale)
    slow = kf_angle_loop(rate, z, FS, tau_s=2.0, update_mask=mask, r_scale=scale)
    np.testing.assert_allclose(fast, slow, atol=1e-8)


def test_stride_bias_is_the_mean_rate_over_whole_strides() -> None:
    n = int(30 * FS)
    _, _, rate = _knee(n)
    period = int(5 * FS)  # exactly 7 cycles of the 1.4 Hz knee
    strides = [(k, k + period) for k in range(0, n - period, period)]
    bias = stride_bias_dps(rate + 1.7, strides)
    assert bias is not None
    assert np.allclose(bias, 1.7, atol=0.05)
    assert stride_bias_dps(rate, []) is None


def test_kf_and_ekf_are_registered() -> None:
    assert {"kf", "ekf", "go", "cf"} <= set(available())


def test_time_constant_mapping_round_trips() -> None:
    for tau in (0.3, 2.0, 20.0):
        for fs in (100.0, 400.0):
            assert time_constant_for_q(q_for_time_constant(tau, fs), fs) == pytest.approx(tau, rel=1e-9)


@pytest.mark.parametrize("x0", [None, 30.0])
def test_vectorised_kf_equals_literal_equations(x0: float | None) -> None:
    rng = np.random.default_rng(2)
    n = 6000
    _, angle, rate = _knee(n)
    z = angle + rng.normal(0, 8, n)
    mask = (np.arange(n) % 140) > 14  # skipped updates around every "foot strike"
    fast = kf_angle(rate + 1.0, z, FS, tau_s=1.5, update_mask=mask, x0_deg=x0, p0_deg2=4.0)
    slow = kf_angle_loop(rate + 1.0, z, FS, tau_s=1.5, update_mask=mask, x0_deg=x0, p0_deg2=4.0)
    np.testing.assert_allclose(fast, slow, atol=1e-8)


def test_kf_removes_drift_and_noise() -> None:
    rng = np.random.default_rng(3)
    n = int(120 * FS)
    _, angle, rate = _knee(n)
    gyro = rate + 0.5 + rng.normal(0, 2, n)  # biased, noisy gyro
    z = angle + rng.normal(0, 15, n)  # very noisy accelerometer angle
    gyro_only = angle[0] + np.cumsum(gyro) / FS
    est = kf_angle(gyro, z, FS)
    rmse = float(np.sqrt(np.mean((est - angle)[int(10 * FS):] ** 2)))
    assert rmse < 3.0
    assert abs(gyro_only[-1] - angle[-1]) > 30  # the integral alone has drifted
    assert rmse < float(np.sqrt(np.mean((z - angle) ** 2))) / 4


def test_kf_coasts_on_gyro_where_updates_are_masked() -> None:
    n = int(20 * FS)
    _, angle, rate = _knee(n)
    z = angle.copy()
    spikes = np.zeros(n, dtype=bool)
    spikes[::140] = True
    spikes = np.convolve(spikes, np.ones(15), mode="same") > 0
    z[spikes] += 80.0  # impact artefacts in the accelerometer angle
    masked = kf_angle(rate, z, FS, update_mask=~spikes, tau_s=0.5)
    unmasked = kf_angle(rate, z, FS, tau_s=0.5)
    err_masked = np.abs(masked - angle).max()
    assert err_masked < 0.5
    assert np.abs(unmasked - angle).max() > 5 * err_masked


def test_kf_initialises_from_accelerometer_angle() -> None:
    n = int(5 * FS)
    _, angle, rate = _knee(n)
    est = kf_angle(rate, angle + 20.0, FS)  # constant accelerometer bias: the estimate follows it
    assert est[0] == pytest.approx(angle[0] + 20.0, abs=0.01)
    assert np.abs(est - angle - 20.0).max() < 0.5


def test_filters_start_where_a_second_of_accelerometer_angles_puts_them() -> None:
    """A segment acceleration of the first instant (here 8 deg, ringing at 7 Hz) does not set the start: the median
    of a second of accelerometer angle minus the gyro's integral does."""
    n = int(5 * FS)
    t, angle, rate = _knee(n)
    z = angle + 8.0 * np.cos(2 * np.pi * 7.0 * t)
    assert abs(start_from_measurement(z, np.ones(n, dtype=bool), rate, 1 / FS) - angle[0]) < 0.5
    late = np.arange(n) >= 50  # the first usable sample later: carried back to sample 0 with the gyroscope
    assert abs(start_from_measurement(z, late, rate, 1 / FS) - angle[0]) < 0.5


def test_ekf_tracks_rotated_accelerations() -> None:
    rng = np.random.default_rng(4)
    n = int(60 * FS)
    t, angle, rate = _knee(n)
    g = 9.81
    # the thigh's knee acceleration in its joint plane: gravity plus some dynamics; the shank's is it rotated
    phi = np.radians(80 + 30 * np.sin(2 * np.pi * 1.4 * t))
    a_thigh = np.column_stack([g * np.cos(phi), g * np.sin(phi)]) + rng.normal(0, 1.0, (n, 2))
    a_shank = _rotate(a_thigh, angle) + rng.normal(0, 1.0, (n, 2))
    est = ekf_angle(rate + 0.8, a_thigh, a_shank, FS, tau_s=0.5, x0_deg=0.0)
    late = slice(int(10 * FS), None)
    assert float(np.sqrt(np.mean((est - angle)[late] ** 2))) < 1.5
    gyro_only = np.cumsum(rate + 0.8) / FS
    assert abs((gyro_only - angle)[-1] - (gyro_only - angle)[0]) > 40  # the integral alone drifts


def test_ekf_matches_kf_for_small_innovations_and_1g() -> None:
    """With |a| = g and isotropic R the EKF is the KF on the accelerometer angle (module docstring)."""
    rng = np.random.default_rng(5)
    n = int(30 * FS)
    t, angle, rate = _knee(n)
    g = 9.80665
    a_thigh = np.column_stack([np.full(n, g), np.zeros(n)])
    z_angle = angle + rng.normal(0, 0.3, n)
    a_shank = _rotate(a_thigh, z_angle)
    mask = (np.arange(n) % 140) > 14
    e = ekf_angle(rate, a_thigh, a_shank, FS, update_mask=mask, x0_deg=angle[0], p0_deg2=1.0)
    k = kf_angle(rate, z_angle, FS, update_mask=mask, x0_deg=angle[0], p0_deg2=1.0)
    assert np.abs(e - k).max() < 0.05


def test_lengths_are_checked() -> None:
    with pytest.raises(ValueError):
        kf_angle(np.zeros(10), np.zeros(9), FS)
    with pytest.raises(ValueError):
        ekf_angle(np.zeros(10), np.zeros((10, 2)), np.zeros((9, 2)), FS)


def test_isotropic_ekf_shortcut_equals_equations_22_to_24() -> None:
    rng = np.random.default_rng(7)
    n = 3000
    t, angle, rate = _knee(n)
    a_thigh = np.column_stack([9.8 + rng.normal(0, 2, n), rng.normal(0, 4, n)])
    a_shank = _rotate(a_thigh, angle + rng.normal(0, 10, n)) + rng.normal(0, 1, (n, 2))
    mask = (np.arange(n) % 140) > 14
    scale = np.where(np.arange(n) < 500, 0.01, 1.0)
    fast = ekf_angle(rate, a_thigh, a_shank, FS, update_mask=mask, r_scale=scale)
    slow = ekf_angle(rate, a_thigh, a_shank, FS, update_mask=mask, r_scale=scale, force_general=True)
    np.testing.assert_allclose(fast, slow, atol=1e-8)
    aniso = ekf_angle(rate, a_thigh, a_shank, FS, update_mask=mask, r_y_mps2_sq=30.0)
    assert np.abs(aniso - fast).max() > 0.1  # a different R does change the estimate


def test_filters_restart_after_a_masked_gap_and_after_a_fill() -> None:
    """``run_per_segment`` restarts at the first measured sample after a fill and moves the fill's angle linearly
    onto the restarted value, so the trace stays continuous and the fill's integral is not carried on."""
    from types import SimpleNamespace

    n = 100
    valid = np.ones(n, dtype=bool)
    valid[70:75] = False  # a masked gap
    measured = valid.copy()
    measured[30:40] = False  # a fill: valid, but a neighbouring stride's samples
    prep = SimpleNamespace(valid=valid, measured=lambda: measured)
    leg = SimpleNamespace(prep=prep, rate_dps=np.zeros(n))
    calls: list[tuple[int, int]] = []

    def fn(a: int, b: int) -> np.ndarray:
        calls.append((a, b))
        return np.full(b - a, 10.0 * len(calls))  # each restart its own level

    out = run_per_segment(leg, fn, np.ones(n, dtype=bool))  # type: ignore[arg-type]
    assert calls == [(0, 40), (40, 70), (75, 100)]
    assert np.all(out[:30] == 10.0) and np.all(out[40:70] == 20.0) and np.all(out[75:] == 30.0)
    assert np.all(np.isnan(out[70:75]))
    ramp = out[29:41]
    assert np.all(np.diff(ramp) > 0) and ramp[0] == 10.0 and ramp[-1] == 20.0  # from the last measured to the restart

    # no usable accelerometer sample after the fill: no start value there, so the filter carries on through it;
    # none in the run after the masked gap: that run has no level and stays NaN
    usable = np.ones(n, dtype=bool)
    usable[40:70] = False
    usable[75:] = False
    calls.clear()
    out = run_per_segment(leg, fn, usable)  # type: ignore[arg-type]
    assert calls == [(0, 70)]
    assert np.all(out[:70] == 10.0) and np.all(np.isnan(out[70:]))
