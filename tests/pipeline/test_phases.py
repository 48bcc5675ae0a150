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


def _gait_rate(t: np.ndarray, stride_s: float, swing_dps: float) -> np.ndarray:
    """A shank sagittal rate [deg/s] of steady gait: a swing lobe, the tibia's roll in mid-stance (a quarter of the
    swing) and the stance dips around them."""
    phase = (t / stride_s) % 1.0
    return swing_dps * (np.exp(-(((phase - 0.75) / 0.08) ** 2)) + 0.25 * np.exp(-(((phase - 0.3) / 0.08) ** 2))
                        - 0.35 * np.exp(-(((phase - 0.55) / 0.05) ** 2))
                        - 0.2 * np.exp(-(((phase - 0.05) / 0.04) ** 2)))


def test_a_shuffle_after_a_brisk_walk_keeps_its_strides() -> None:
    """A brisk walk (swings of 450 deg/s) and, after 3 s of standing, a rehabilitation shuffle (130 deg/s, slower
    cadence) in one session: the shuffle's swings are a quarter of the session's and failed the session-wide rule
    (no shuffle stride at all); among their neighbours they are swings."""
    fs = 100.0
    brisk = _gait_rate(np.arange(int(12 * 0.95 * fs)) / fs, 0.95, 450.0)
    shuffle = _gait_rate(np.arange(int(12 * 1.6 * fs)) / fs, 1.6, 130.0)
    w = np.concatenate([brisk, np.zeros(int(3 * fs)), shuffle])
    ev = detect_gait_events(w, fs)
    t0_shuffle = (brisk.size + 3 * fs) / fs
    starts_s = np.array([a for a, _, _ in ev.strides]) / fs
    assert np.sum(starts_s > t0_shuffle) >= 9
    assert np.sum(starts_s < brisk.size / fs) >= 9
    mid_swing_phase = np.where(ev.ms / fs < t0_shuffle, ev.ms / fs / 0.95, (ev.ms / fs - t0_shuffle) / 1.6) % 1.0
    assert np.all(np.abs(mid_swing_phase - 0.75) < 0.05)  # no tibia roll taken for a swing, brisk or slow


def test_a_lobe_half_the_height_of_its_neighbours_is_no_swing() -> None:
    """Step-ups beside a walk: lobes of 110 deg/s next to lobes of 55 (the leading and the trailing leg's shank),
    far below the walk's swings. Neither rule may make swings of the small ones, so no bout forms of them."""
    fs = 100.0
    walk = _gait_rate(np.arange(int(12 * 1.1 * fs)) / fs, 1.1, 380.0)
    t = np.arange(int(20 * fs)) / fs
    lobe_times, heights = np.arange(1.0, 19.0, 1.8), np.tile([110.0, 60.0, 60.0, 110.0], 3)[:10]
    steps = sum(h * np.exp(-(((t - c) / 0.15) ** 2)) - 0.4 * h * np.exp(-(((t - c - 0.5) / 0.15) ** 2))
                for c, h in zip(lobe_times, heights, strict=True))
    ev = detect_gait_events(np.concatenate([walk, np.zeros(int(3 * fs)), steps]), fs)
    found = np.interp(ev.ms / fs - (walk.size / fs + 3), t, steps, left=np.nan)
    assert np.sum(found > 90) >= 4  # the step-ups' large lobes stand out among their neighbours
    assert not np.any(found < 90)  # the small ones never


def _step_to_rate(t: np.ndarray, cycle_s: float, swing_dps: float, swing_s: float = 0.35) -> np.ndarray:
    """A shank sagittal rate [deg/s] of step-to gait: one swing lobe of ~``swing_s`` per cycle, its toe-off and
    heel-strike dips, the tibia's roll in stance, and a pause of double support that fills the rest of the cycle."""
    tau, at, k = t % cycle_s, cycle_s - 0.35, swing_s / 0.44
    return swing_dps * (np.exp(-(((tau - at) / (0.1 * k)) ** 2))
                        - 0.4 * np.exp(-(((tau - at + 0.27 * k) / (0.06 * k)) ** 2))
                        - 0.3 * np.exp(-(((tau - at - 0.27 * k) / (0.05 * k)) ** 2))
                        + 0.15 * np.exp(-(((tau - 0.6) / 0.15) ** 2)))


@pytest.mark.parametrize("cycle_s", [2.6, 2.9])
def test_step_to_gait_with_its_pauses_keeps_its_strides(cycle_s: float) -> None:
    """Step-to gait with crutches: two steps and two pauses make a cycle of 2-3 s (and more) in which each leg's
    swing lobe lasts ~0.35 s, 85-90 % stance. Every cycle is a stride."""
    fs = 100.0
    ev = detect_gait_events(_step_to_rate(np.arange(int(12 * cycle_s * fs)) / fs, cycle_s, 200.0), fs)
    strides = np.array(ev.strides)
    assert len(strides) >= 10
    stance = (strides[:, 1] - strides[:, 0]) / (strides[:, 2] - strides[:, 0])
    assert np.all(stance > 0.85)
    assert np.allclose(np.diff(strides[:, 0]) / fs, cycle_s, atol=0.02)
