"""pipeline.phases: gait events against simulator truth, and no strides where nobody walks."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.params import WALKING
from pipeline.phases import detect_gait_events, shank_sagittal_dps
from pipeline.simulate import SimConfig, simulate_session

QUIET = dict(packet_loss=0.0, outages_per_min=0.0, sync_offset_ms=0.0, clock_drift_ppm=0.0)


def _shank(pattern: str, seed: int, **kw):
    sim = simulate_session(SimConfig(pattern=pattern, seed=seed, n_strides=16, bout_strides=8,
                                     activities=("standing", "sitting"), **QUIET, **kw))
    s = next(x for x in sim.streams if x.sensor_id == "L-shank")
    return sim, s, shank_sagittal_dps(s.gyr)


@pytest.mark.parametrize("pattern", ["normal", "slow", "stiff-knee", "crouch"])
def test_events_match_truth(pattern: str) -> None:
    sim, s, w = _shank(pattern, seed=1)
    ev = detect_gait_events(w, s.fs_hz, shank_acc_mps2=s.acc)
    truth = sim.truth["left"]
    hs_t = np.array([s.t_s[a] for a, _, _ in ev.strides])
    to_t = np.array([s.t_s[t] for _, t, _ in ev.strides])
    steady = [st for st in truth.strides if st.steady]
    assert len(ev.strides) >= len(steady) - 1
    for st in steady:
        k = int(np.argmin(np.abs(hs_t - st.t_start_s)))
        assert abs(hs_t[k] - st.t_start_s) < 0.04
        assert abs(to_t[k] - st.t_toe_off_s) < 0.05
    # mid-swing between toe-off and heel strike, mid-stance between heel strike and the next toe-off
    ok = (ev.to >= 0) & (ev.hs >= 0)
    assert np.all((ev.to[ok] < ev.ms[ok]) & (ev.ms[ok] < ev.hs[ok]))
    has = ev.mst >= 0
    assert np.all(ev.mst[has] > ev.hs[has])


def test_gyro_only_heel_strike_is_close() -> None:
    sim, s, w = _shank("normal", seed=2)
    ev = detect_gait_events(w, s.fs_hz)
    hs_t = np.array([s.t_s[a] for a, _, _ in ev.strides])
    err = [np.min(np.abs(hs_t - st.t_start_s)) for st in sim.truth["left"].strides if st.steady]
    assert np.median(err) < 0.04


def test_no_strides_without_walking() -> None:
    rng = np.random.default_rng(0)
    fs = 100.0
    t = np.arange(0, 60, 1 / fs)
    standing = 3.0 * rng.standard_normal(t.size)  # noise and sway only
    assert detect_gait_events(standing, fs).strides == []
    # sit-to-stand / stand-to-sit: a few isolated shank rotations of 60-90 deg/s, seconds apart
    sts = standing.copy()
    for t0 in (10.0, 25.0, 40.0):
        sts += 80.0 * np.exp(-0.5 * ((t - t0) / 0.3) ** 2) - 40.0 * np.exp(-0.5 * ((t - t0 - 0.9) / 0.3) ** 2)
    assert detect_gait_events(sts, fs).strides == []


def test_no_stride_spans_a_masked_gap() -> None:
    sim, s, w = _shank("normal", seed=3)
    valid = np.ones(w.size, dtype=bool)
    full = detect_gait_events(w, s.fs_hz, valid=valid)
    a, _, b = full.strides[len(full.strides) // 2]
    valid[(a + b) // 2:(a + b) // 2 + 30] = False
    cut = detect_gait_events(w, s.fs_hz, valid=valid)
    assert len(cut.strides) < len(full.strides)
    for a2, _, b2 in cut.strides:
        assert valid[a2:b2 + 1].all()


def test_no_stride_ends_next_to_a_masked_gap() -> None:
    """A heel strike in a hole must not be replaced by the last measured point before it."""
    sim, s, w = _shank("normal", seed=3)
    valid = np.ones(w.size, dtype=bool)
    full = detect_gait_events(w, s.fs_hz, valid=valid)
    _, _, b = full.strides[len(full.strides) // 2]
    valid[b - 2:b + 40] = False  # the hole swallows the true heel strike
    guard = int(WALKING.phases.gap_guard_s * s.fs_hz)
    for a2, _, b2 in detect_gait_events(w, s.fs_hz, valid=valid).strides:
        assert valid[max(a2 - guard, 0):b2 + guard + 1].all()


def test_the_tibias_roll_over_the_foot_is_no_swing() -> None:
    """In mid-stance the tibia rolls forward over the foot: a positive lobe of its own (here 90 deg/s against 350 in
    swing, as in fast walking). With one per stride, half of the lobes are stance lobes; they must not count as
    swings (the median of all lobes fell between the two kinds and let them through: no stride at all)."""
    fs, stride_s = 100.0, 0.9
    t = np.arange(int(20 * stride_s * fs)) / fs
    phase = (t / stride_s) % 1.0
    swing = 350 * np.exp(-(((phase - 0.75) / 0.08) ** 2))
    roll = 90 * np.exp(-(((phase - 0.3) / 0.08) ** 2))
    dips = -120 * np.exp(-(((phase - 0.55) / 0.05) ** 2)) - 60 * np.exp(-(((phase - 0.05) / 0.04) ** 2))
    ev = detect_gait_events(swing + roll + dips, fs)
    assert len(ev.strides) >= 15
    assert np.all(np.abs(((ev.ms / fs / stride_s) % 1.0) - 0.75) < 0.05)  # every mid-swing is a swing's
