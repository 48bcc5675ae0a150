"""Regression on the real recordings in ../shared/data/real (skipped where the folder is absent)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.real_data import BIOMECHZOO_CSV, TAN_DIR, load_biomechzoo, load_tan_steps, real_data_available
from pipeline.assignment import side_verdict
from pipeline.phases import detect_gait_events, shank_sagittal_dps
from pipeline.session import process_session
from tests.conftest import skip_without_real_data

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def zoo():
    skip_without_real_data(real_data_available(BIOMECHZOO_CSV), "biomechZoo trial")
    streams, vicon = load_biomechzoo()
    return process_session(streams), vicon


def _errors(leg_result, vicon):
    t, ref = vicon[leg_result.leg]
    v = np.interp(leg_result.t_s, t, ref)
    inside = np.zeros(v.size, dtype=bool)
    peak_err = []
    for s in leg_result.strides:
        m = (leg_result.t_s >= s.t_start_s) & (leg_result.t_s <= s.t_end_s)
        inside |= m
        swing = (leg_result.t_s >= s.t_toe_off_s) & m
        peak_err.append(s.peak_swing_flexion_deg - v[swing].max())
    e = leg_result.angle_deg[inside] - v[inside]
    return np.array(peak_err), e


def test_biomechzoo_strides_and_zero_mean_error(zoo) -> None:
    """Achieved at the time of writing: 8 strides per leg; zero-mean RMSE over the strides ~3.8 (right) / ~4.8
    (left) deg as recorded, ~3.5 / ~2.5 deg once the Xsens and Vicon clocks are aligned within the +-30 ms the data
    README states (the best lag is 10-30 ms on both legs; the error is mostly that lag times the knee rate)."""
    res, vicon = zoo
    assert set(res.legs) == {"left", "right"}
    for lr in res.legs.values():
        assert len(lr.strides) >= 7
        _, e = _errors(lr, vicon)
        assert np.sqrt(np.mean((e - e.mean()) ** 2)) < 5.5
        t, ref = vicon[lr.leg]
        ok = np.isfinite(lr.angle_deg)
        best = min(float(np.std(lr.angle_deg[ok] - np.interp(lr.t_s[ok] + lag, t, ref)))
                   for lag in np.arange(-0.03, 0.0301, 0.005))
        assert best < 4.0


def test_biomechzoo_swing_peak(zoo) -> None:
    """Right leg: absolute swing-peak error (mean ~ -1.6 deg). The left Vicon reference carries an offset (its
    minimum is -10 deg), so there the peak is compared after removing the mean offset over the strides."""
    res, vicon = zoo
    peak_r, _ = _errors(res.legs["right"], vicon)
    assert abs(np.mean(peak_r)) < 3.0
    assert np.max(np.abs(peak_r)) < 4.0
    peak_l, e_l = _errors(res.legs["left"], vicon)
    assert abs(np.mean(peak_l - e_l.mean())) < 5.0


def test_tan_heel_strike_and_toe_off_timing() -> None:
    skip_without_real_data(real_data_available(TAN_DIR), "Tan et al. steps")
    hs_err, to_err = [], []
    for w in load_tan_steps():
        ev = detect_gait_events(shank_sagittal_dps(w.shank_gyr_dps), w.fs_hz, min_bout_peaks=1,
                                shank_acc_mps2=w.shank_acc_mps2)
        hs, to = ev.hs[ev.hs >= 0], ev.to[ev.to >= 0]
        assert hs.size and to.size
        hs_err.append((hs[np.argmin(np.abs(hs - w.hs_idx))] - w.hs_idx) / w.fs_hz)
        to_err.append((to[np.argmin(np.abs(to - w.to_idx))] - w.to_idx) / w.fs_hz)
    hs_err, to_err = np.abs(hs_err), np.abs(to_err)
    # achieved: HS within 20 ms in all 20 windows (impact onset), TO within 20 ms (shank minimum + 40 ms)
    assert np.mean(hs_err <= 0.02) >= 0.9
    assert np.median(to_err) <= 0.02


def test_real_trial_sides_are_read_and_a_swap_is_caught(zoo) -> None:
    """The frontal-plane weight shift of the real Xsens thighs: mirrored between the legs as labelled, and every
    stride out of trends when the left and right labels of all four sensors are exchanged."""
    res, _ = zoo
    shift = {leg: lr.diagnostics.weight_shift_dps for leg, lr in res.legs.items()}
    assert side_verdict(shift["left"], shift["right"]) == "as_labelled"
    streams, _ = load_biomechzoo()
    other = {"left": "right", "right": "left"}
    swapped = process_session([dataclasses.replace(s, leg=other[s.leg]) for s in streams])
    assert any("left and right labels look swapped" in w for w in swapped.warnings)
    assert all("side_in_doubt" in s.quality_reasons and s.quality < 0.5
               for lr in swapped.legs.values() for s in lr.strides)
