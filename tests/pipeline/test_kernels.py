"""The compiled loops (:mod:`pipeline.kernels`) give the numpy/scipy paths' values bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.signal import sosfiltfilt

from pipeline import kernels, prepare, signal_utils
from pipeline.params import WALKING
from pipeline.types import RawSensorStream


def test_kernels_are_compiled() -> None:
    """The test environment installs numba (the `fast` extra is part of `dev`), so the compiled loops are what the
    suite runs and what the tests below compare with the numpy paths; without it they would be silently absent."""
    assert kernels.filtfilt_columns is not None
    assert kernels.hermite_eval is not None
    assert kernels.central_slopes is not None


@pytest.mark.parametrize("shape", [(180_000, 6), (5_000, 3), (5_000, 1), (4_001,), (19,), (40, 2)])
@pytest.mark.parametrize(("cutoff_hz", "fs_hz"), [(10.0, 100.0), (4.0, 100.0), (15.0, 100.0), (6.0, 52.0)])
def test_lowpass_equals_sosfiltfilt(shape: tuple[int, ...], cutoff_hz: float, fs_hz: float) -> None:
    x = np.random.default_rng(len(shape) * 1000 + shape[0]).standard_normal(shape) * 300.0
    sos = signal_utils._butter_sos(2, cutoff_hz, fs_hz)
    padlen = min(x.shape[0] - 1, 3 * (2 * len(sos) + 1))
    expected = sosfiltfilt(sos, x, axis=0, padlen=padlen)
    got = signal_utils.lowpass(x, cutoff_hz, fs_hz)
    assert got.shape == expected.shape
    assert np.array_equal(got, expected)


@pytest.mark.parametrize("shape", [(5_000, 4), (5_000, 5), (3_000, 2), (3_000, 1)])
@pytest.mark.parametrize("order", [2, 4])
def test_lowpass_of_any_width_and_order_equals_sosfiltfilt(shape: tuple[int, ...], order: int) -> None:
    """Single-section filters run three columns side by side (a last group of one or two repeats a column);
    higher orders take the general section loop."""
    x = np.random.default_rng(shape[1] * 10 + order).standard_normal(shape) * 300.0
    sos = signal_utils._butter_sos(order, 8.0, 100.0)
    padlen = min(x.shape[0] - 1, 3 * (2 * len(sos) + 1))
    assert np.array_equal(signal_utils.lowpass(x, 8.0, 100.0, order=order),
                          sosfiltfilt(sos, x, axis=0, padlen=padlen))


def test_lowpass_of_a_strided_view_equals_sosfiltfilt() -> None:
    x = np.random.default_rng(3).standard_normal((3_000, 6))[:, ::2]
    sos = signal_utils._butter_sos(2, 10.0, 100.0)
    assert np.array_equal(signal_utils.lowpass(x, 10.0, 100.0), sosfiltfilt(sos, x, axis=0, padlen=9))


def _irregular(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.sort(np.arange(n) / 100.0 + rng.normal(0.0, 0.0004, n))
    t = np.delete(t, np.r_[np.arange(500, n, 3_000), np.arange(1_200, 1_260)])  # short and one long gap
    return t, rng.standard_normal((t.size, 6)) * 50.0


@pytest.mark.parametrize("grid", ["uniform", "beyond_both_ends", "unsorted"])
def test_interpolation_equals_numpy_path(grid: str, monkeypatch: pytest.MonkeyPatch) -> None:
    t, x = _irregular(7, 20_000)
    if grid == "uniform":
        t_new = t[0] + np.arange(19_000) / 100.0
    elif grid == "beyond_both_ends":
        t_new = np.linspace(t[0] - 0.5, t[-1] + 0.5, 25_000)
    else:
        t_new = np.random.default_rng(1).uniform(t[0], t[-1], 50_000)
    got = prepare._interp_columns(t_new, t, x, 0.1)
    monkeypatch.setattr(prepare, "hermite_eval", None)
    expected = prepare._interp_columns(t_new, t, x, 0.1)
    assert np.array_equal(got, expected)
    g = int(np.argmax(np.diff(t)))  # the long gap: a straight line across, no cubic overshoot
    inside = (t_new > t[g]) & (t_new < t[g + 1])
    assert inside.any()
    lo, hi = np.minimum(x[g], x[g + 1]), np.maximum(x[g], x[g + 1])
    assert np.all((got[inside] >= lo - 1e-9) & (got[inside] <= hi + 1e-9))


@pytest.mark.parametrize("layout", ["contiguous", "strided"])
def test_row_norm_and_cross_rows_equal_numpy(layout: str) -> None:
    rng = np.random.default_rng(11)
    a = rng.standard_normal((20_000, 6)) * 7.0
    b = rng.standard_normal((20_000, 6)) * 3.0
    a, b = (a[:, :3], b[:, 3:]) if layout == "strided" else (np.ascontiguousarray(a[:, :3]), b[:, 3:].copy())
    assert np.array_equal(signal_utils.row_norm(a), np.linalg.norm(a, axis=1))
    assert np.array_equal(signal_utils.cross_rows(a, b), np.cross(a, b))
    v = np.array([0.3, -0.8, 0.52])
    assert np.array_equal(signal_utils.cross_rows(a, v), np.cross(a, v))


def test_periodic_fill_equals_numpy_path(monkeypatch: pytest.MonkeyPatch) -> None:
    fs = 100.0
    t = np.arange(6_000) / fs
    rng = np.random.default_rng(5)
    x = np.column_stack([np.sin(2 * np.pi * t / 1.1 + k) * (3 + k) for k in range(6)])
    x += rng.normal(0.0, 0.05, x.shape)
    gaps = [(t[2_000], t[2_030]), (t[4_000], t[4_012]), (t[100], t[140])]
    got, filled, kept = prepare.periodic_fill(t, x, gaps, fs)
    monkeypatch.setattr(prepare, "shifted_context", None)
    expected, filled0, kept0 = prepare.periodic_fill(t, x, gaps, fs)
    assert filled == filled0 and kept == kept0 and len(filled) >= 2
    assert np.array_equal(got, expected)
    assert not np.array_equal(got[2_001:2_030], x[2_001:2_030])  # the hole was really filled


@pytest.mark.parametrize("units", [("deg/s", "g"), ("rad/s", "m/s2")])
@pytest.mark.parametrize("damage", ["none", "nan", "unsorted"])
def test_to_si_equals_numpy_path(units: tuple[str, str], damage: str, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(2)
    n = 5_000
    t = np.arange(n) / 100.0
    gyr = rng.standard_normal((n, 3)) * np.array([1.0, 300.0, 1e-3])
    acc = rng.standard_normal((n, 3)) * np.array([1e-5, 2.0, 40.0])
    if damage == "nan":
        gyr[100, 1] = np.nan
        acc[200, 2] = np.inf
    elif damage == "unsorted":
        t[300], t[301] = t[301], t[300]
        t[400] = t[399]
    s = RawSensorStream(sensor_id="x", leg="left", segment="thigh", fs_hz=100.0, t_s=t, gyr=gyr, acc=acc,
                        gyro_unit=units[0], acc_unit=units[1])
    got = prepare.to_si(s)
    monkeypatch.setattr(prepare, "si_block", None)
    expected = prepare.to_si(s)
    for a, b in zip(got, expected, strict=True):
        assert np.array_equal(a, b)
    assert got[0].size == (n if damage == "none" else n - 2 if damage == "nan" else n - 1)


@pytest.mark.parametrize("run_len", [1, 2, 3, 4, 5])
def test_saturation_mask_equals_numpy_path(run_len: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(run_len)
    gyr = rng.uniform(-3.0, 3.0, (4_000, 3))
    gyr[:, 1] *= 3.0  # the other axes stay below the clipping threshold
    peak = np.abs(gyr[:, 1]).max()
    for start in rng.integers(0, 3_990, 40):  # clipped runs of 1-6 samples, a few at the ends
        gyr[start:start + rng.integers(1, 7), 1] = peak * np.sign(rng.standard_normal())
    gyr[:2, 1] = peak
    gyr[-3:, 1] = -peak
    params = dataclasses.replace(WALKING.prepare, saturation_run=run_len)
    got = prepare.saturation_mask(gyr, params)
    monkeypatch.setattr(prepare, "saturated_runs", None)
    expected = prepare.saturation_mask(gyr, params)
    assert expected.any() and not expected.all()
    assert np.array_equal(got, expected)
