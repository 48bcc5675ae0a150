"""Running: foot strikes, gait-cycle windows, impact masks, 7 Hz filter (Rhudy et al. 2024, Sect. 2.2.2)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.axes import orient_axes
from pipeline.constants import G_MPS2
from pipeline.estimators import get_estimator
from pipeline.estimators.cf import complementary_filter
from pipeline.estimators.kf import kf_leg
from pipeline.params import RUNNING, WALKING
from pipeline.phases import detect_gait_events
from pipeline.prepare import prepare_leg
from pipeline.running import (
    build_running_leg_input,
    cycle_window_mask,
    detect_foot_strikes,
    find_cycles,
    gait_cycles,
    impact_mask,
    looks_like_running,
    lowpass_7hz,
    shank_axis_sign,
    thigh_axis_sign,
)
from pipeline.session import process_session
from pipeline.simulate import SimConfig, SimSession, simulate_session
from pipeline.tuning import tune_time_constant

TAU_RANGE_S = RUNNING.tuning.tau_range_s

FS = 200.0


def _gait_acc(stride_s: float, impact_g: float, n_strides: int = 30, seed: int = 0,
              whip_g: float = 3.5) -> tuple[np.ndarray, np.ndarray]:
    """Shank accelerations (N,3) of a gait with jittered strides: gravity, a smooth swing 'whip' of ``whip_g``
    (larger than the impact's raw magnitude when ``impact_g`` is small) and a damped 28 Hz impact ringing at every
    foot strike. Returns the accelerations and the true strike indices."""
    rng = np.random.default_rng(seed)
    lengths = stride_s * (1 + 0.04 * rng.standard_normal(n_strides))
    strikes_s = 0.5 + np.concatenate(([0.0], np.cumsum(lengths)))
    n = int((strikes_s[-1] + 0.5) * FS)
    t = np.arange(n) / FS
    acc = np.zeros((n, 3))
    acc[:, 2] = G_MPS2
    for a, b in zip(strikes_s[:-1], strikes_s[1:], strict=True):
        u = (t - a) / (b - a)
        inside = (u >= 0) & (u < 1)
        bump = np.where(inside, np.exp(-0.5 * ((u - 0.7) / 0.06) ** 2), 0.0)
        acc[:, 0] += whip_g * G_MPS2 * bump
    for s in strikes_s:
        u = t - s
        ring = np.where(u >= 0, np.exp(-np.clip(u, 0, None) / 0.012) * np.sin(2 * np.pi * 28 * np.clip(u, 0, None)),
                        0.0)
        acc[:, 2] += impact_g * G_MPS2 * ring
        acc[:, 0] += 0.3 * impact_g * G_MPS2 * ring
    acc += 0.05 * rng.standard_normal(acc.shape)
    return acc, np.round(strikes_s * FS).astype(int)


def test_foot_strikes_found_even_when_the_swing_peaks_are_higher() -> None:
    acc, truth = _gait_acc(0.72, impact_g=3.0)
    mag = np.linalg.norm(acc, axis=1)
    assert mag[truth].max() < mag.max()  # raw magnitude peaks are the swings, not the impacts
    found = detect_foot_strikes(acc, FS)
    assert found.size == truth.size
    assert np.abs(found - truth).max() <= 3  # within 15 ms of the true strike


def test_cycles_skip_gaps_and_implausible_intervals() -> None:
    acc, truth = _gait_acc(0.72, impact_g=4.0)
    valid = np.ones(acc.shape[0], dtype=bool)
    valid[truth[10] + 20: truth[10] + 40] = False  # packet loss inside cycle 10
    strikes = np.delete(truth, 20)  # a missed strike: cycle 19 spans two strides
    cycles = gait_cycles(strikes, FS, valid)
    starts = [a for a, _ in cycles]
    assert truth[10] not in starts
    assert truth[19] not in starts
    assert len(cycles) == truth.size - 1 - 3  # the gap cycle and the doubled cycle (replacing two) are dropped


def test_fit_windows_cover_40_to_80_percent() -> None:
    cycles = [(100, 300), (300, 500)]
    mask = cycle_window_mask(cycles, 600)
    assert mask.sum() == 160
    assert mask[180] and mask[259] and not mask[260] and not mask[179]
    assert not mask[:180].any() and not mask[500:].any()


def test_impact_mask_is_five_percent_of_the_cycle_each_side() -> None:
    strikes = np.array([200, 344, 488, 632])  # 144-sample (0.72 s) cycles
    mask = impact_mask(strikes, 800, FS)
    w = int(np.ceil(0.05 * 144))
    for s in strikes:
        assert mask[s - w:s + w + 1].all()
        assert not mask[s - w - 2] and not mask[s + w + 2]
    assert mask.sum() == strikes.size * (2 * w + 1)


@pytest.mark.parametrize(("stride_s", "impact_g", "running"), [(0.72, 5.0, True), (1.1, 1.5, False),
                                                                (0.72, 0.8, False), (1.0, 5.0, False)])
def test_running_is_recognised_by_cadence_and_impacts(stride_s: float, impact_g: float, running: bool) -> None:
    acc, _ = _gait_acc(stride_s, impact_g=impact_g, whip_g=2.0)
    cycles = find_cycles(acc, FS)
    assert looks_like_running(cycles) is running


def test_lowpass_is_zero_lag_and_respects_gaps() -> None:
    t = np.arange(int(10 * FS)) / FS
    slow = np.sin(2 * np.pi * 1.5 * t)
    fast = 0.5 * np.sin(2 * np.pi * 25 * t)
    valid = np.ones(t.size, dtype=bool)
    valid[1000:1040] = False
    x = slow + fast
    x[1000:1040] = 1e3  # garbage inside the gap must not leak into its neighbours
    y = lowpass_7hz(x, FS, valid)
    inner = np.r_[100:900, 1140:1900]
    assert np.abs(y[inner] - slow[inner]).max() < 0.02  # 25 Hz removed, 1.5 Hz passed without lag
    assert np.abs(y[:1000]).max() < 2


@pytest.fixture(scope="module")
def running_sim() -> SimSession:
    return simulate_session(SimConfig(pattern="running", fs_hz=FS, seed=3, n_strides=40, legs=("left",)))


def test_simulated_running_strikes(running_sim: SimSession) -> None:
    """On the project simulator's running pattern (impacts weaker than the swing whip in raw magnitude)."""
    sim = running_sim
    by = {s.segment: s for s in sim.streams}
    prep = prepare_leg("left", by["thigh"], by["shank"])
    cycles = find_cycles(prep.acc_shank_mps2, prep.fs_hz, prep.valid)
    truth = sim.truth["left"].heel_strikes_s
    found = prep.t_s[cycles.strikes]
    err = np.array([np.min(np.abs(truth - f)) for f in found])
    assert found.size >= truth.size - 2
    assert np.median(err) < 0.03
    assert looks_like_running(cycles)


def test_running_session_auto_uses_the_extended_kalman_filter(running_sim: SimSession) -> None:
    """Target: RMSE <= 3.5 deg and peak swing flexion within a few degrees, without any reference-based tuning."""
    sim = running_sim
    res = process_session(sim.streams, activity="running")
    leg = res.legs["left"]
    assert leg.strides and {s.estimator for s in leg.strides} == {"ekf"}
    # the EKF is running's primary estimator: no running stride is a fallback
    assert all(s.activity == "running" and not s.fallback for s in leg.strides)
    assert leg.diagnostics.n_fallback == 0 and leg.diagnostics.tau_s is not None
    truth = sim.truth["left"]
    inside = np.zeros(leg.t_s.size, dtype=bool)
    for a, b in truth.bouts_s:
        inside |= (leg.t_s >= a) & (leg.t_s <= b)
    err = (leg.angle_deg - truth.angle_at(leg.t_s))[inside & np.isfinite(leg.angle_deg)]
    assert float(np.sqrt(np.mean(err ** 2))) <= 3.5
    peaks = np.array([s.peak_swing_flexion_deg for s in leg.strides])
    true_peaks = np.array([s.peak_swing_flexion_deg for s in truth.strides if s.steady])
    assert abs(float(np.median(peaks)) - float(np.median(true_peaks))) <= 3.0
    assert 85.0 <= float(np.median(peaks)) <= 125.0


def test_running_strides_of_an_assumed_level_are_capped_like_walking(running_sim: SimSession) -> None:
    """Without a calibration a running stride's level rests on the assumed standing flexion: never >= 0.8
    (pipeline.quality); with the measured value the same strides are vouched for again."""
    from pipeline.types import KneeCalibration

    res = process_session(running_sim.streams, activity="running")
    strides = res.legs["left"].strides
    assert strides and all("assumed_level" in s.quality_reasons and s.quality <= 0.75 for s in strides)
    cal = {"left": KneeCalibration(standing_knee_deg=running_sim.truth["left"].stand_knee_deg, method="goniometer")}
    calibrated = process_session(running_sim.streams, activity="running", calibration=cal).legs["left"].strides
    assert calibrated and all("assumed_level" not in s.quality_reasons for s in calibrated)
    assert max(s.quality for s in calibrated) > 0.8


def test_unknown_activity_is_detected_as_running(running_sim: SimSession) -> None:
    res = process_session(running_sim.streams, activity="unknown")
    assert res.legs["left"].strides[0].estimator == "ekf"
    diag = res.legs["left"].diagnostics
    assert diag.activity == "running" and diag.running is not None and diag.running.cycles >= 20


def test_thigh_axis_sign_is_recovered_from_the_swing_peak(running_sim: SimSession) -> None:
    by = {s.segment: s for s in running_sim.streams}
    prep = prepare_leg("left", by["thigh"], by["shank"])
    data, _ = build_running_leg_input(prep, RUNNING)
    cycles = data.running_cycles
    j1, j2 = data.axes.j1, data.axes.j2
    for start in (j1, -j1):
        got = thigh_axis_sign(start, j2, prep.gyr_thigh_rps, prep.gyr_shank_rps, cycles, prep.fs_hz)
        np.testing.assert_allclose(got, j1)


def _rearfoot_shank_rate_dps(fs_hz: float = 100.0, stride_s: float = 0.7, n_strides: int = 30
                             ) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """A running shank's sagittal rate [deg/s] from foot strike to foot strike: the loading dip after a rearfoot
    strike (-700 at 18 %) deeper than both the early-swing minimum (-350 at 40 %) and the swing peak (+600 at
    75 %). Returns the rate and the (strike, next strike) cycles."""
    keys = np.array([(0, 0), (0.05, -300), (0.18, -700), (0.3, -200), (0.4, -350), (0.55, 0), (0.75, 600),
                     (0.92, 100), (1.0, 0)], dtype=float)
    t = np.arange(int(n_strides * stride_s * fs_hz)) / fs_hz
    rate = np.interp((t / stride_s) % 1.0, keys[:, 0], keys[:, 1])
    per = int(round(stride_s * fs_hz))
    return rate, [(k * per, (k + 1) * per) for k in range(n_strides - 1)]


def test_shank_axis_sign_comes_from_the_late_swing_not_the_largest_rate() -> None:
    """Where the stance dip outweighs the swing peak, the walking convention (largest excursion positive) turns the
    shank axis round; the late swing of the foot-strike cycle turns it back, from either start."""
    rate, cycles = _rearfoot_shank_rate_dps()
    j = np.array([0.0, 0.0, 1.0])
    g2 = np.deg2rad(rate)[:, None] * j
    g1 = 0.4 * np.roll(g2, 10, axis=0)
    _, flipped = orient_axes(j, j, g1, g2)
    np.testing.assert_allclose(flipped, -j)
    for start in (j, -j):
        np.testing.assert_allclose(shank_axis_sign(start, g2, cycles), j)


def test_running_toe_off_is_not_taken_from_the_loading_dip() -> None:
    """Walking's 0.3 s toe-off search reaches back into a running stride's loading response; its deeper dip made
    every stance share ~18 % and every stride implausible. The running preset searches 0.2 s."""
    rate, _ = _rearfoot_shank_rate_dps()
    valid = np.ones(rate.size, dtype=bool)
    assert detect_gait_events(rate, 100.0, valid, params=WALKING.phases).strides == []
    strides = detect_gait_events(rate, 100.0, valid, params=RUNNING.phases).strides
    assert len(strides) >= 25
    share = [100 * (t - a) / (b - a) for a, t, b in strides]
    assert all(35 <= x <= 50 for x in share)  # true toe-off near the early-swing minimum, 35-40 %


def test_kf_update_mask_skips_impacts_and_keeps_swing_windows(running_sim: SimSession) -> None:
    by = {s.segment: s for s in running_sim.streams}
    prep = prepare_leg("left", by["thigh"], by["shank"])
    data, info = build_running_leg_input(prep, RUNNING)
    update = data.acc_update_mask
    strikes = find_cycles(prep.acc_shank_mps2, prep.fs_hz, prep.valid).strikes
    assert not update[strikes].any()
    a, b = data.running_cycles[5]
    assert update[a + int(0.6 * (b - a))]
    assert info.acc_update_pct < 60
    angle, diag = kf_leg(data, tau_s=0.5)
    assert diag.tuning is None
    assert np.isfinite(angle[prep.valid]).mean() > 0.95


def test_tuning_trusts_a_cleaner_gyroscope_longer(running_sim: SimSession) -> None:
    by = {s.segment: s for s in running_sim.streams}
    prep = prepare_leg("left", by["thigh"], by["shank"])
    data, _ = build_running_leg_input(prep, RUNNING)
    tau, diag = tune_time_constant(data)
    assert TAU_RANGE_S[0] <= tau <= TAU_RANGE_S[1] and diag.strides >= 20
    # a gyro whose per-stride closure scatters more (a wandering bias) must lean on the accelerometer sooner
    rng = np.random.default_rng(0)
    wander = np.repeat(rng.normal(0, 3.0, prep.n // 100 + 1), 100)[:prep.n]
    tau_noisy, _ = tune_time_constant(data, data.rate_dps + wander)
    assert tau_noisy < 0.7 * tau


@pytest.mark.parametrize("name", ["cf", "kf"])
def test_filters_ignore_the_accelerometer_angle_at_impacts(running_sim: SimSession, name: str) -> None:
    """Rhudy et al.: no measurement update +-5 % of the cycle around a foot strike, for CF, KF and EKF alike."""
    by = {s.segment: s for s in running_sim.streams}
    prep = prepare_leg("left", by["thigh"], by["shank"])
    data, _ = build_running_leg_input(prep, RUNNING)
    est = get_estimator(name)
    clean, _ = est(data)
    strikes = find_cycles(prep.acc_shank_mps2, prep.fs_hz, prep.valid).strikes
    around = impact_mask(strikes, prep.n, prep.fs_hz)
    data = replace(data, acc_angle_deg=np.where(around, data.acc_angle_deg + 60.0, data.acc_angle_deg))
    hit, _ = est(data)
    ok = np.isfinite(clean)
    assert ok.mean() > 0.9
    # (a strike detected at the edge of a standing period may shift the standing zero by hundredths of a degree)
    assert np.abs(hit[ok] - clean[ok]).max() < 0.05
    naive = complementary_filter(data.rate_dps, data.acc_angle_deg, prep.fs_hz, prep.valid)
    assert np.nanmax(np.abs(naive - complementary_filter(data.rate_dps, np.where(around, data.acc_angle_deg - 60.0,
                                                                                 data.acc_angle_deg),
                                                         prep.fs_hz, prep.valid))) > 1.0


def test_holes_filled_from_neighbouring_strides_do_not_move_the_filters_level() -> None:
    """A fill's rate is a neighbouring stride's, whose integral misses the lost one's by several degrees: the EKF must
    restart after it (pipeline.filter_inputs.run_per_segment) instead of carrying that error over the next strides.
    Running, bursty BLE loss of 5 %: carried through the fills, this session's left leg spread its strides' peak
    errors with an SD of 12 deg (up to 25 deg off at trend quality)."""
    from bench.matching import TREND_QUALITY, match_strides

    sim = simulate_session(SimConfig(pattern="running", fs_hz=128.0, seed=3, duration_s=90, packet_samples=20,
                                     packet_loss=0.05, loss_model="bursty", loss_burst_packets=4.0))
    res = process_session(sim.streams, activity="running")
    for leg, truth in sim.truth.items():
        strides = res.legs[leg].strides
        assert any(s.quality_reasons and "bridged_gap" in s.quality_reasons for s in strides)  # fills are there
        err = np.array([strides[i].peak_swing_flexion_deg - truth.strides[j].peak_swing_flexion_deg
                        for i, j in match_strides(strides, truth.strides) if strides[i].quality >= TREND_QUALITY])
        assert err.size > 40
        assert err.std() < 2.5, (leg, err.std())
        assert np.abs(err - np.median(err)).max() < 8.0, (leg, np.abs(err - np.median(err)).max())


def _dragged_estimators(monkeypatch: pytest.MonkeyPatch, t_drift: float) -> None:
    """Every estimator's angle drifts towards extension at 4 deg/s from ``t_drift`` on (its accelerometer updates
    dragging it, as on an independent simulator)."""
    import pipeline.policy as policy

    real = policy.get_estimator

    def dragged(name: str):  # noqa: ANN202
        estimate = real(name)

        def run(leg):  # noqa: ANN001, ANN202
            angle, diag = estimate(leg)
            return angle - 4.0 * np.clip(leg.prep.t_s - t_drift, 0.0, None), diag
        return run

    monkeypatch.setattr(policy, "get_estimator", dragged)


def test_a_running_filter_dragged_off_its_level_leaves_the_trends(running_sim: SimSession,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """From 60 % of the run on the filter's angle drifts towards extension at 4 deg/s. Without the cycle-mean
    gravity's level (``FusionParams.gravity_level`` off, as where whole cycles are missing) GO's zero comes back every
    stride, so the filter's level against GO strays: those strides go out of trends (``level_wander``); the strides
    before, and every stride of the run without the drift, stay."""
    from pipeline.types import KneeCalibration

    params = replace(RUNNING, fusion=replace(RUNNING.fusion, gravity_level=False))
    cal = {"left": KneeCalibration(standing_knee_deg=running_sim.truth["left"].stand_knee_deg)}
    clean = process_session(running_sim.streams, activity="running", calibration=cal, params=params).legs["left"]
    assert clean.strides and not any("level_wander" in s.quality_reasons for s in clean.strides)
    t_drift = clean.t_s[0] + 0.6 * (clean.t_s[-1] - clean.t_s[0])
    _dragged_estimators(monkeypatch, t_drift)
    strides = process_session(running_sim.streams, activity="running", calibration=cal,
                              params=params).legs["left"].strides
    late = [s for s in strides if s.t_start_s > t_drift + 3.0]
    early = [s for s in strides if s.t_end_s < t_drift]
    assert late and all("level_wander" in s.quality_reasons and s.quality < 0.5 for s in late)
    assert early and not any("level_wander" in s.quality_reasons for s in early)


def test_the_cycle_mean_gravity_pulls_a_dragged_filter_back(running_sim: SimSession,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The same drift with the cycle-mean gravity's level (the default): every whole cycle's level comes from
    gravity, so the late strides keep their peaks (typically within 1 deg of the undisturbed run where the drift
    reaches 10-60 deg; a stride next to a cycle without a level, or at the run's end where the shift falls towards the
    standing after it, by up to 2.8 deg per cycle at this drift) instead of leaving the trends."""
    clean = process_session(running_sim.streams, activity="running").legs["left"]
    t_drift = clean.t_s[0] + 0.6 * (clean.t_s[-1] - clean.t_s[0])
    _dragged_estimators(monkeypatch, t_drift)
    leg = process_session(running_sim.streams, activity="running").legs["left"]
    by_start = {round(s.t_start_s, 2): s for s in clean.strides}
    late = [(s, by_start[round(s.t_start_s, 2)]) for s in leg.strides
            if s.t_start_s > t_drift + 3.0 and round(s.t_start_s, 2) in by_start]
    assert len(late) >= 5
    diffs = np.abs([s.peak_swing_flexion_deg - c.peak_swing_flexion_deg for s, c in late])
    assert np.median(diffs) < 1.0 and diffs.max() < 5.0


def test_a_knee_that_is_no_hinge_keeps_its_level_over_a_long_run() -> None:
    """90 s of running with 3-D hip and knee motion (the tibia turning as the knee flexes), longer than the quiet
    standing around it can bridge: with both Eq. 2 axes free they tilt together and the trend strides' swing peaks
    read 3-7 deg low; with the thigh's axis from its own rotation (``RunningParams.thigh_axis``) they stay within
    1.5 deg on either leg."""
    from bench.matching import data_gaps, score_leg

    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, activities=("standing",), duration_s=90.0,
                                     bout_strides=400, impact_g=6.0, knee_3d=1.0, hip_3d=1.0, seed=7))

    def median_errors(thigh_axis: str) -> list[float]:
        params = replace(RUNNING, running=replace(RUNNING.running, thigh_axis=thigh_axis))
        legs = process_session(sim.streams, activity="running", params=params).legs
        errors = [score_leg(legs[leg], truth, data_gaps(sim, leg)).peak_err_trend for leg, truth in sim.truth.items()]
        assert all(len(e) > 80 for e in errors)
        return [float(np.median(e)) for e in errors]

    assert max(abs(e) for e in median_errors("principal")) < 1.5
    assert min(median_errors("hinge")) < -3.0
