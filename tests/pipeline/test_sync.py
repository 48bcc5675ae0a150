"""Thigh/shank clock offset (pipeline.sync): the joint-centre constraint (Seel Eq. 5) where the hinge one is flat."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest

import pipeline.axes
from bench.real_data import BIOMECHZOO_CSV, load_biomechzoo, real_data_available
from pipeline.axes import (
    LagEstimate,
    angular_acceleration,
    estimate_centre_lag_s,
    fit_margin_mask,
    one_valley,
)
from pipeline.params import RUNNING, WALKING
from pipeline.prepare import nominal_fs, prepare_leg_si, to_si
from pipeline.session import process_session
from pipeline.signal_utils import lowpass_runs_many
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import (
    ClockFit,
    _centre_inputs,
    _checked_by_centre,
    _fitted_axes,
    clock_model,
    shock_mask,
    stride_clock_runaway,
    stride_timing_drift,
    synchronised_leg,
)
from pipeline.walking import fit_gyros
from tests.conftest import skip_without_real_data
from tests.pipeline.legs import leg_streams as _leg_streams
from tests.pipeline.legs import prepared as _prepared

# straight walking (no turns): the hinge constraint carries no timing; clocks exact unless a lag is injected
_STRAIGHT = dict(pattern="normal", duration_s=90.0, walking_turns=False, sync_offset_ms=0.0, clock_drift_ppm=0.0)


@pytest.fixture(scope="module")
def straight():
    return simulate_session(SimConfig(seed=7, **_STRAIGHT))


@pytest.mark.parametrize("lag_ms", [15.0, -10.0])
def test_injected_lag_in_straight_walking_is_recovered(straight, lag_ms: float) -> None:
    """The hinge constraint gives no model without turns; the joint-centre profile recovers the lag within 2 ms."""
    for leg in ("left", "right"):
        thigh, shank = _leg_streams(straight.streams, leg, lag_ms / 1000)
        prep, g1, g2, axes = _prepared(thigh, shank)
        assert clock_model(prep, g1, g2, axes, WALKING.sync).offset_s is None  # hinge alone: flat
        synced = synchronised_leg(leg, thigh, shank, WALKING)
        assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms - lag_ms) < 2.0


def test_no_lag_is_invented_on_synchronised_sensors(straight) -> None:
    for leg in ("left", "right"):
        synced = synchronised_leg(leg, *_leg_streams(straight.streams, leg), WALKING)
        assert synced.shank_lag_ms is None or abs(synced.shank_lag_ms) < 1.5


def test_centre_lag_is_none_without_motion() -> None:
    """Still sensors (independent noise on each): the Eq. 5 cost is flat over the lag, so no estimate."""
    n, fs = 3000, 100.0
    rng = np.random.default_rng(0)
    g1, g2 = (1e-3 * rng.standard_normal((n, 3)) for _ in range(2))
    a1, a2 = (np.array([0.0, 0.0, 9.81]) + 1e-2 * rng.standard_normal((n, 3)) for _ in range(2))
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    j = np.array([0.0, 1.0, 0.0])
    far = np.ones(n, dtype=bool)
    assert estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, j, j, far, fs, slice(0, n), 0.06)[0] is None


@pytest.mark.realdata
def test_centre_lag_on_hardware_synchronised_real_trial() -> None:
    """biomechZoo's Xsens sensors share one clock: the joint-centre profile finds no lag worth correcting (within
    4 ms) where the hinge constraint alone suggests a false 10-18 ms."""
    skip_without_real_data(real_data_available(BIOMECHZOO_CSV), "biomechZoo trial")
    streams, _ = load_biomechzoo()
    for leg in ("left", "right"):
        prep, g1, g2, axes = _prepared(*_leg_streams(streams, leg))
        fs = prep.fs_hz
        a1, a2 = (np.nan_to_num(a) for a in lowpass_runs_many((prep.acc_thigh_mps2, prep.acc_shank_mps2),
                                                                prep.valid, WALKING.axes.fit_cutoff_hz, fs))
        gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
        far = fit_margin_mask(prep.valid, fs)
        lag, _ = estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, far, fs, slice(0, prep.n),
                                       WALKING.sync.max_lag_s)
        assert lag is not None and abs(lag) < 0.004


def test_the_centre_cue_runs_on_a_bounded_number_of_windows(straight, monkeypatch: pytest.MonkeyPatch) -> None:
    """However long a recording without turns, the costly centre profile is evaluated on at most
    ``max_centre_windows`` windows spread over it."""
    calls: list[slice] = []

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(args[10])
        return estimate_centre_lag_s(*args, **kwargs)

    monkeypatch.setattr("pipeline.sync.estimate_centre_lag_s", counted)
    prep, g1, g2, axes = _prepared(*_leg_streams(straight.streams, "left", 0.012))
    params = dataclasses.replace(WALKING.sync, window_s=10.0, max_centre_windows=3)
    offset = clock_model(prep, g1, g2, axes, params, WALKING.axes).offset_s
    windows = sorted({(w.start, w.stop) for w in calls})
    assert len(windows) == 3  # of 9 windows
    assert windows[0][0] == 0 and windows[-1][1] == prep.n  # the first and the last: spread over the session
    assert len(calls) == 3  # each read once: the profile refits its centres, wherever the search starts
    assert offset is not None and abs(offset - 0.012) < 0.003


def test_the_centre_profile_at_a_high_rate_reads_the_lag_of_every_lag_from_a_coarse_pass(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """At 500 Hz the +-60 ms hold 61 lags: fitted every 10 ms first and then to the sample around the least, the
    profile reads the lag that fitting every lag reads, with less than half the centre fits."""
    sim = simulate_session(SimConfig(seed=3, fs_hz=500.0, **{**_STRAIGHT, "duration_s": 30.0}))
    prep, g1, g2, axes = _prepared(*_leg_streams(sim.streams, "left", 0.017))
    fs = prep.fs_hz
    a1, a2, gd1, gd2, far = _centre_inputs(prep, g1, g2, WALKING.sync, WALKING.axes)
    fits = [0]
    lsq = pipeline.axes._lsq_centres

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        fits[0] += 1
        return lsq(*args, **kwargs)

    monkeypatch.setattr("pipeline.axes._lsq_centres", counted)
    reads = {}
    for step_s in (0.0, WALKING.sync.centre_lag_step_s):
        fits[0] = 0
        lag, _ = estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, far, fs, slice(0, prep.n),
                                       WALKING.sync.max_lag_s, step_s=step_s)
        reads[step_s] = (lag, fits[0])
    (every, n_every), (coarse, n_coarse) = reads.values()
    assert every is not None and abs(every - 0.017) < 0.003  # the lag injected
    assert coarse == pytest.approx(every, abs=1e-4)
    assert n_coarse < 0.5 * n_every


# a 10 m walk test: ~8 s of walking between 1 s of quiet standing, shorter than two 40 s windows (a tune seed)
_SHORT = dict(pattern="normal", duration_s=10.0, standing_s=1.0, sync_offset_ms=0.0, clock_drift_ppm=0.0)


@pytest.fixture(scope="module")
def short_walk():
    return simulate_session(SimConfig(seed=3, **_SHORT))


def test_short_session_lag_is_corrected(short_walk) -> None:
    """Too short for two hinge windows: the joint-centre cue on the two halves recovers an 18 ms offset."""
    for leg in ("left", "right"):
        synced = synchronised_leg(leg, *_leg_streams(short_walk.streams, leg, 0.018), WALKING)
        assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms - 18.0) < 3.0


def test_short_session_without_lag_is_not_moved(short_walk) -> None:
    for leg in ("left", "right"):
        synced = synchronised_leg(leg, *_leg_streams(short_walk.streams, leg), WALKING)
        assert synced.shank_lag_ms is None or abs(synced.shank_lag_ms) < 2.0


def test_short_session_with_too_short_halves_is_left_alone(short_walk) -> None:
    prep, g1, g2, axes = _prepared(*_leg_streams(short_walk.streams, "left", 0.018))
    params = dataclasses.replace(WALKING.sync, short_window_s=prep.n / prep.fs_hz / 2 + 0.5)
    assert clock_model(prep, g1, g2, axes, params, WALKING.axes).offset_s is None
    assert clock_model(prep, g1, g2, axes, WALKING.sync, WALKING.axes).offset_s is not None


@pytest.mark.realdata
def test_short_real_trial_offset_is_corrected_and_none_invented() -> None:
    """The 10 s hardware-synchronised biomechZoo trial: nothing applied as recorded; an imposed 15 ms shank offset
    corrected to within 4 ms (the cue reads -0.3 .. -3.7 ms there at zero)."""
    skip_without_real_data(real_data_available(BIOMECHZOO_CSV), "biomechZoo trial")
    streams, _ = load_biomechzoo()
    for leg in ("left", "right"):
        assert synchronised_leg(leg, *_leg_streams(streams, leg), WALKING).shank_lag_ms is None
        synced = synchronised_leg(leg, *_leg_streams(streams, leg, 0.015), WALKING)
        assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms - 15.0) < 4.0


@pytest.mark.parametrize("seed", [0, 2])
def test_a_drift_beyond_one_crystals_tolerance_is_followed(seed: int) -> None:
    """Two crystals can run ~200 ppm and more apart (tolerance, temperature, age): a 5-minute leg whose shank runs
    300-400 ppm off its thigh gets that drift (the old 150 ppm clip left it 150-250 ppm off: 25-40 ms at the ends)."""
    sim = simulate_session(SimConfig(pattern="normal", seed=seed, duration_s=300.0, bout_strides=12, legs=("left",),
                                     clock_drift_ppm=150.0))
    true_ppm = sim.info["sensors"]["L-shank"]["drift_ppm"] - sim.info["sensors"]["L-thigh"]["drift_ppm"]
    assert 300 < abs(true_ppm) < WALKING.sync.max_drift * 1e6
    diag = process_session(sim.streams, activity="walking").legs["left"].diagnostics
    assert diag is not None and diag.shank_drift_ppm is not None
    assert abs(diag.shank_drift_ppm - true_ppm) < 40


def test_heel_strike_shocks_are_left_out_of_the_centre_cue() -> None:
    """10 g heel strikes ring through the shank and reach the thigh weakened: the two accelerometers do not measure
    one rigid knee-centre acceleration then. The samples around them are masked (not the quiet ones), and the
    joint-centre cue recovers an injected lag as without shocks."""
    shocked = simulate_session(SimConfig(seed=4, impact_g=10.0, **_STRAIGHT))
    calm = simulate_session(SimConfig(seed=4, impact_g=0.0, **_STRAIGHT))
    for sim, masked in ((shocked, True), (calm, False)):
        thigh, shank = _leg_streams(sim.streams, "left")
        prep = _prepared(thigh, shank)[0]
        low = lowpass_runs_many((prep.acc_thigh_mps2, prep.acc_shank_mps2), prep.valid, WALKING.axes.fit_cutoff_hz,
                                prep.fs_hz)
        mask = shock_mask(((prep.acc_thigh_mps2, low[0]), (prep.acc_shank_mps2, low[1])), prep.valid, prep.fs_hz,
                          WALKING.sync)
        hs = np.searchsorted(prep.t_s, sim.truth["left"].heel_strikes_s)
        hs = hs[(hs > 0) & (hs < prep.n)]
        share = mask[hs].mean()
        assert (share > 0.9) if masked else (mask.mean() < 0.01), share
    for leg in ("left", "right"):
        synced = synchronised_leg(leg, *_leg_streams(shocked.streams, leg, 0.012), WALKING)
        assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms - 12.0) < 3.0


# four minutes of walking with turns between bouts, exact clocks unless a drift is injected
_LONG = dict(pattern="normal", duration_s=240.0, sync_offset_ms=0.0, clock_drift_ppm=0.0)


@pytest.fixture(scope="module")
def long_walk():
    return simulate_session(SimConfig(seed=11, **_LONG))


def _drifting(shank, offset_s: float, drift: float):
    """The shank's stamps ``offset_s`` late at mid-recording and running ``drift`` [s/s] fast."""
    t = np.asarray(shank.t_s, dtype=float)
    t_mid = 0.5 * (t[0] + t[-1])
    return dataclasses.replace(shank, t_s=t + offset_s + drift * (t - t_mid))


def test_drifting_shank_clock_is_followed_beyond_the_search_range(long_walk) -> None:
    """350 ppm (a shank clock off by more than a crystal's tolerance) on a 25 ms offset: the lag runs from -17 to
    +67 ms over the recording, beyond the +-60 ms each window searches. Each window searches around the line of the
    ones before it, so the whole line is found: rate within 20 ppm, mid-session offset within 2 ms."""
    for leg in ("left", "right"):
        thigh, shank = _leg_streams(long_walk.streams, leg)
        synced = synchronised_leg(leg, thigh, _drifting(shank, 0.025, 350e-6), WALKING)
        assert not synced.clock_disagreement
        assert synced.shank_drift_ppm is not None and abs(synced.shank_drift_ppm - 350.0) < 20.0
        assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms - 25.0) < 2.0


def test_window_lags_are_placed_where_the_cue_is(long_walk, monkeypatch: pytest.MonkeyPatch) -> None:
    """Under a 300 ppm drift each window's lag lies within 1.5 ms of the true lag at the window's weighted time (at
    the windows' middles they were off by up to 6 ms: the hinge cue speaks in the turns)."""
    import pipeline.sync as sync_module

    thigh, shank = _leg_streams(long_walk.streams, "left")
    shank = _drifting(shank, 0.0, 300e-6)
    t_mid = 0.5 * (shank.t_s[0] + shank.t_s[-1])
    seen: list[tuple[float, float]] = []
    line_model = sync_module._line_model

    def spy(prep, windows, params, lag_of, drifting=True, weight=None, wide=False):  # noqa: ANN001, ANN202
        def rec(w: slice, centre_s: float) -> LagEstimate | None:
            est = lag_of(w, centre_s)
            if est is not None:
                seen.append((float(np.average(prep.t_s[w], weights=weight[w])), est.lag_s))
            return est
        return line_model(prep, windows, params, rec, drifting, weight, wide)

    monkeypatch.setattr(sync_module, "_line_model", spy)
    prep, g1, g2, axes = _prepared(thigh, shank)
    clock_model(prep, g1, g2, axes, WALKING.sync, WALKING.axes)
    assert len(seen) >= 3
    for t, lag in seen:
        assert abs(lag - 300e-6 * (t - t_mid)) < 0.0015


def test_an_oscillator_without_crystal_is_followed_and_kept_in_trends(long_walk) -> None:
    """800 ppm: no pair of crystal clocks drifts so fast, but calibrated RC oscillators (+-250-500 ppm each) do. The
    window lags follow it (``SyncParams.max_line_drift``): rate within 40 ppm, mid-session offset within 2 ms, and
    the leg's strides stay in trends like the other leg's."""
    thigh, shank = _leg_streams(long_walk.streams, "left")
    synced = synchronised_leg("left", thigh, _drifting(shank, 0.0, 800e-6), WALKING)
    assert not synced.clock_disagreement
    assert synced.shank_drift_ppm is not None and abs(synced.shank_drift_ppm - 800.0) < 40.0
    assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms) < 2.0
    streams = [(_drifting(s, 0.0, 800e-6) if s.leg == "left" and s.segment == "shank" else s)
               for s in long_walk.streams]
    res = process_session(streams, activity="walking")
    for leg in ("left", "right"):
        lr = res.legs[leg]
        assert not lr.diagnostics.clock_disagreement
        assert len(lr.strides) > 100 and not any("clock_disagreement" in s.quality_reasons for s in lr.strides)
        assert sum(s.quality >= 0.5 for s in lr.strides) > 0.9 * len(lr.strides)
    assert not any("clock_disagreement" in w for w in res.warnings)


def test_a_steep_line_the_stride_timing_does_not_show_leaves_the_timing_unknown(
        long_walk, monkeypatch: pytest.MonkeyPatch) -> None:
    """Window lags on an 800 ppm line over a leg whose clocks agree (what a gyro bias drifting over the session can
    make of the hinge cue): re-stamped by that line, the leg's stride timing shows the line itself left over, so
    nothing is corrected and the leg's timing is unknown. The same line over a shank that does run 800 ppm fast
    leaves no drift in the stride timing and is applied."""
    import pipeline.sync as sync

    monkeypatch.setattr(sync, "clock_model", lambda *a, **k: ClockFit(0.0, 800e-6))
    thigh, shank = _leg_streams(long_walk.streams, "left")
    synced = synchronised_leg("left", thigh, shank, WALKING)
    assert synced.shank_lag_ms is None and synced.shank_drift_ppm is None and synced.clock_disagreement
    drifting = synchronised_leg("left", thigh, _drifting(shank, 0.0, 800e-6), WALKING)
    assert drifting.shank_drift_ppm == 800.0


def test_a_line_too_steep_for_the_windows_keeps_the_leg_out_of_trends(long_walk, monkeypatch: pytest.MonkeyPatch
                                                                      ) -> None:
    """Window lags that agree on a line steeper than the windows can see (``SyncParams.max_line_drift``) are no
    clock the pipeline can correct: nothing is corrected, the leg says so, and every stride of it carries
    ``clock_disagreement`` below the trend threshold, while the other leg keeps its strides in trends."""
    import pipeline.sync as sync

    real = sync._line_model

    def steep(prep, windows, params, lag_of, drifting=True, weight=None, wide=False):  # noqa: ANN001, ANN202
        if prep.leg == "right":
            return real(prep, windows, params, lag_of, drifting, weight, wide)
        t_mid = float(prep.t_s[prep.n // 2])
        line = 1.2 * params.max_line_drift
        return real(prep, windows, params,
                    lambda w, c: LagEstimate(line * (float(prep.t_s[(w.start + w.stop) // 2]) - t_mid)), drifting)

    monkeypatch.setattr(sync, "_line_model", steep)
    res = process_session(long_walk.streams, activity="walking")
    left, right = res.legs["left"], res.legs["right"]
    assert left.diagnostics.clock_disagreement and not right.diagnostics.clock_disagreement
    assert [w for w in res.warnings if "clock_disagreement" in w] == [
        w for w in res.warnings if w.startswith("left leg: its thigh and shank clocks run apart")]
    assert any(w.startswith("left leg: its thigh and shank clocks") for w in res.warnings)
    assert left.strides and all("clock_disagreement" in s.quality_reasons and s.quality < 0.5 for s in left.strides)
    assert len(right.strides) > 100 and not any("clock_disagreement" in s.quality_reasons for s in right.strides)
    assert sum(s.quality >= 0.5 for s in right.strides) > 0.9 * len(right.strides)


@pytest.mark.parametrize("drift", [1500e-6, -3000e-6])
def test_clock_too_fast_for_the_windows_is_followed_through_the_stride_timing(long_walk, drift: float) -> None:
    """Beyond ~1000 ppm a 40 s window's lag smears past the search range and the window lags fall silent; the
    thigh's swing peak, which follows the shank's by a near-constant time, still shows the drift. The shank is
    re-stamped by it and the windows find what is left: rate within 20 ppm, offset within 1 ms, and every stride's
    swing peak within 0.6 deg of the same walk on one clock, all of them in trends."""
    one_clock = process_session(long_walk.streams, activity="walking").legs["right"]
    streams = [(_drifting(s, 0.0, drift) if s.leg == "right" and s.segment == "shank" else s)
               for s in long_walk.streams]
    right = process_session(streams, activity="walking").legs["right"]
    diag = right.diagnostics
    assert not diag.clock_disagreement
    assert abs(diag.shank_drift_ppm - drift * 1e6) < 20 and abs(diag.shank_lag_ms) < 1.0
    assert len(right.strides) == len(one_clock.strides)
    for got, ref in zip(right.strides, one_clock.strides, strict=True):
        assert abs(got.t_start_s - ref.t_start_s) < 0.02
        assert abs(got.peak_swing_flexion_deg - ref.peak_swing_flexion_deg) < 0.6
        assert got.quality == ref.quality


@pytest.mark.parametrize("drift", [900e-6, -1200e-6])
def test_clocks_started_together_are_followed_through_the_stride_timing(long_walk, drift: float) -> None:
    """Two clocks started together and drifting 900 / -1200 ppm apart are 108 / 144 ms apart at the middle of the
    4-minute walk: after the re-stamp by the stride timing's drift that whole lag is left, beyond the windows'
    +-60 ms. The whole re-stamped leg finds it: lag at mid-session within 2 ms, rate within 20 ppm, every swing
    peak within 0.6 deg of the same walk on one clock."""
    one_clock = process_session(long_walk.streams, activity="walking").legs["right"]
    _, shank = _leg_streams(long_walk.streams, "right")
    t = np.asarray(shank.t_s, dtype=float)
    mid_lag_s = drift * 0.5 * (t[-1] - t[0])
    streams = [(_drifting(s, mid_lag_s, drift) if s.leg == "right" and s.segment == "shank" else s)
               for s in long_walk.streams]
    right = process_session(streams, activity="walking").legs["right"]
    diag = right.diagnostics
    assert not diag.clock_disagreement
    assert abs(diag.shank_drift_ppm - drift * 1e6) < 20 and abs(diag.shank_lag_ms - 1000 * mid_lag_s) < 2.0
    assert len(right.strides) == len(one_clock.strides)
    for got, ref in zip(right.strides, one_clock.strides, strict=True):
        assert abs(got.peak_swing_flexion_deg - ref.peak_swing_flexion_deg) < 0.6


def test_clock_too_fast_for_the_stride_timing_keeps_the_leg_out_of_trends(long_walk) -> None:
    """5000 ppm moves the lag by 1.2 s over the 4-minute walk: too fast for the windows and beyond the stride
    timing's own search around each mid-swing. Nothing is corrected and the leg is flagged; the other leg, and the
    same leg at a crystal's 300 ppm, are not."""
    streams = [(_drifting(s, 0.0, 5000e-6) if s.leg == "right" and s.segment == "shank" else s)
               for s in long_walk.streams]
    res = process_session(streams, activity="walking")
    assert res.legs["right"].diagnostics.clock_disagreement
    assert all("clock_disagreement" in s.quality_reasons for s in res.legs["right"].strides)
    assert not res.legs["left"].diagnostics.clock_disagreement
    # the flagged leg's own stride times are not judged against the other leg's (they may lie anywhere)
    assert not any(w.startswith("right leg:") and "dropped" in w for w in res.warnings)
    crystal = [(_drifting(s, 0.0, 300e-6) if s.leg == "right" and s.segment == "shank" else s)
               for s in long_walk.streams]
    assert not process_session(crystal, activity="walking").legs["right"].diagnostics.clock_disagreement


def test_an_uncorrected_leg_beyond_two_crystals_is_kept_out_of_trends(long_walk, monkeypatch: pytest.MonkeyPatch
                                                                     ) -> None:
    """Window lags that see no line (a drifting gyro bias with a 3-D knee and packet loss can silence them) leave
    the leg uncorrected. With a 350 ppm shank that is +-42 ms at the ends of the 4-minute walk: beyond what two
    crystals drift apart (``SyncParams.crystal_drift``), the stride timing shows it and the leg's strides leave the
    trends; at a crystal's 100 ppm they stay."""
    import pipeline.sync as sync

    monkeypatch.setattr(sync, "clock_model", lambda *a, **k: ClockFit(None))
    for drift, flagged in ((350e-6, True), (100e-6, False)):
        streams = [(_drifting(s, 0.0, drift) if s.leg == "right" and s.segment == "shank" else s)
                   for s in long_walk.streams]
        res = process_session(streams, activity="walking")
        right = res.legs["right"]
        assert right.diagnostics.shank_drift_ppm is None
        assert right.diagnostics.clock_disagreement is flagged
        assert all(("clock_disagreement" in st.quality_reasons) is flagged for st in right.strides)
        assert not res.legs["left"].diagnostics.clock_disagreement


def test_stride_timing_check_needs_enough_strides() -> None:
    """A thigh peak that drifts 3000 ppm against the shank's mid-swing is flagged over 60 strides in 66 s, but
    not from 10 strides, nor from 25 strides within 24 s (no verdict: False)."""
    fs = 100.0
    t = np.arange(8000) / fs

    def case(ms: np.ndarray) -> bool:
        thigh = np.zeros(t.size)
        thigh[ms - 12 - np.round(3000e-6 * t[ms] * fs).astype(int)] = 1.0
        return stride_clock_runaway(t, thigh, ms, fs, WALKING.sync)

    assert case(np.arange(100, 100 + 60 * 110, 110))
    assert not case(np.arange(100, 100 + 10 * 110, 110))
    assert not case(np.arange(100, 100 + 25 * 100, 100))


def test_stride_timing_check_on_long_recordings() -> None:
    """600 strides (11 minutes): a 600 ppm drift is seen, and no drift where there is none."""
    fs = 100.0
    ms = np.arange(100, 100 + 600 * 110, 110)
    t = np.arange(ms[-1] + 200) / fs

    def thigh(drift: float) -> np.ndarray:
        out = np.zeros(t.size)
        out[ms + np.round((0.10 - drift * t[ms]) * fs).astype(int)] = 1.0
        return out

    assert stride_clock_runaway(t, thigh(600e-6), ms, fs, WALKING.sync)
    assert not stride_clock_runaway(t, thigh(0.0), ms, fs, WALKING.sync)


def test_a_slow_bout_after_a_brisk_one_is_no_clock_drift() -> None:
    """The thigh's swing peak leads the shank's by a share of the stride (here 12 %): 30 brisk strides of 1.0 s, a
    pause, then 30 slow ones of 1.8 s lengthen the lead from 120 to 216 ms, which a slope over time alone read as a
    drift of ~1000 ppm (both legs of such sessions flagged on an independent simulator). Beside the stride period
    no drift is seen; a real 1500 ppm drift on the same walk still is."""
    fs = 100.0
    brisk = 200 + np.arange(30) * 100
    slow = brisk[-1] + 500 + np.arange(30) * 180
    ms = np.concatenate([brisk, slow])
    period = np.concatenate([np.full(30, 1.0), np.full(30, 1.8)])
    t = np.arange(ms[-1] + 200) / fs
    rng = np.random.default_rng(0)

    def thigh(drift: float) -> np.ndarray:
        lead = 0.12 * period + 0.004 * rng.standard_normal(ms.size) - drift * t[ms]
        out = np.zeros(t.size)
        out[ms - np.round(lead * fs).astype(int)] = 1.0
        return out

    assert not stride_clock_runaway(t, thigh(0.0), ms, fs, WALKING.sync)
    assert stride_clock_runaway(t, thigh(1500e-6), ms, fs, WALKING.sync)


def test_a_change_of_gait_between_bouts_is_no_clock_drift() -> None:
    """Four bouts of 20 strides at one pace; in the last two the thigh's swing peak leads the shank's by 110 ms more
    (another style of walking: pivoting steps, a thigh peak that moved). The session's slope reads that as ~1000 ppm,
    but within each bout the lead holds still: no drift. A real 1500 ppm drift moves it within the bouts too."""
    fs = 100.0
    starts = 200 + np.arange(4) * 2600
    ms = np.concatenate([s + np.arange(20) * 107 for s in starts])
    t = np.arange(ms[-1] + 200) / fs
    step = np.repeat([0.0, 0.0, 0.11, 0.11], 20)
    rng = np.random.default_rng(1)

    def thigh(drift: float) -> np.ndarray:
        lead = 0.18 + step + 0.004 * rng.standard_normal(ms.size) - drift * t[ms]
        out = np.zeros(t.size)
        out[ms - np.round(lead * fs).astype(int)] = 1.0
        return out

    seen = stride_timing_drift(t, thigh(0.0), ms, fs, WALKING.sync)
    assert seen is not None and seen.low > WALKING.sync.crystal_drift  # the session's slope alone would claim it
    assert not stride_clock_runaway(t, thigh(0.0), ms, fs, WALKING.sync, limit=WALKING.sync.crystal_drift)
    assert stride_clock_runaway(t, thigh(-1500e-6), ms, fs, WALKING.sync, limit=WALKING.sync.crystal_drift)


def test_one_scattered_window_is_noise_not_a_runaway_clock() -> None:
    """Three windows over 90 s: lags 10, 11, 40 ms do not lie on any line within ``agree_s`` (a noisy cue): no
    correction, no flag. Lags on a line steeper than the windows can see (3600 ppm) are a runaway clock; on a
    crystal's (200 ppm) or an RC oscillator's (900 ppm) a drift."""
    from types import SimpleNamespace

    from pipeline.sync import _line_model

    prep = SimpleNamespace(t_s=np.arange(9000) / 100.0, n=9000)
    windows = [slice(0, 3000), slice(3000, 6000), slice(6000, 9000)]

    def fit(lags_ms: list[float]):  # noqa: ANN202
        return _line_model(prep, windows, WALKING.sync, lambda w, c: LagEstimate(lags_ms[windows.index(w)] / 1000))

    scattered = fit([10.0, 11.0, 40.0])
    assert scattered.offset_s is None and not scattered.disagreement
    runaway = fit([10.0 - 108.0, 10.0, 10.0 + 108.0])
    assert runaway.offset_s is None and runaway.disagreement
    oscillator = fit([10.0 - 27.0, 10.0, 10.0 + 27.0])
    assert oscillator.offset_s is not None and abs(oscillator.drift - 900e-6) < 1e-6 and not oscillator.disagreement
    crystal = fit([10.0 - 6.0, 10.0, 10.0 + 6.0])
    assert crystal.offset_s is not None and abs(crystal.drift - 200e-6) < 1e-6 and not crystal.disagreement


def test_a_faint_window_weighs_less_in_the_clock_line() -> None:
    """Three hinge windows over 90 s at 10, 10 and 16 ms, the last with a standard error of 5 ms (most of its turns
    lost), the others 0.5 ms: the weighted line stays at 10 ms with ~10 ppm of drift, where equal weights would read
    a 100 ppm drift (the 16 ms window alone) and an offset of 11 ms."""
    from types import SimpleNamespace

    from pipeline.sync import _line_model

    prep = SimpleNamespace(t_s=np.arange(9000) / 100.0, n=9000)
    windows = [slice(0, 3000), slice(3000, 6000), slice(6000, 9000)]
    lags_ms, ses_ms = [10.0, 10.0, 16.0], [0.5, 0.5, 5.0]

    def fit(with_se: bool):  # noqa: ANN202
        def lag_of(w: slice, centre_s: float) -> LagEstimate:
            i = windows.index(w)
            return LagEstimate(lags_ms[i] / 1000, ses_ms[i] / 1000 if with_se else None)
        return _line_model(prep, windows, WALKING.sync, lag_of)

    weighted, equal = fit(True), fit(False)
    assert equal.offset_s is not None and abs(equal.drift - 100e-6) < 1e-6
    assert weighted.offset_s is not None and abs(weighted.drift) < 15e-6 and abs(weighted.offset_s - 0.010) < 3e-4


def test_lost_packets_do_not_set_the_clock() -> None:
    """10 % of 20-sample packets lost per sensor at 128 Hz (a 156 ms hole each; seeds outside the sweep's): every
    leg's thigh-shank offset at mid-session within 4.5 ms (an uncorrected leg counts its whole offset), 1.1 ms on
    average. Three causes had set the clock from the holes: the axis fit and the hinge cue read the filled holes
    (their timing is the neighbouring strides'), and each candidate lag compared its own set of samples, so the
    cost curve measured which samples were compared (max 10.5 ms, mean 2.2 ms here; without the filled holes
    7.9 / 1.3 ms)."""
    errors = []
    for seed in range(18, 34):
        sim = simulate_session(SimConfig(pattern="normal", seed=seed, duration_s=90.0, bout_strides=12, fs_hz=128.0,
                                         packet_samples=20, packet_loss=0.10))
        clocks = sim.info["sensors"]
        for leg in ("left", "right"):
            shank, thigh = clocks[f"{leg[0].upper()}-shank"], clocks[f"{leg[0].upper()}-thigh"]
            # shank minus thigh stamp error at mid-session [ms]: offsets plus the rate difference over 45 s
            drift_ppm = shank["drift_ppm"] - thigh["drift_ppm"]
            true_ms = shank["sync_offset_ms"] - thigh["sync_offset_ms"] + 45e-3 * drift_ppm
            synced = synchronised_leg(leg, *_leg_streams(sim.streams, leg), WALKING)
            assert synced.prep.filled_s  # the case holds filled holes
            errors.append(abs((synced.shank_lag_ms or 0.0) - true_ms))
    assert max(errors) < 4.5, errors
    assert np.mean(errors) < 1.1, errors


@pytest.mark.parametrize(("seed", "leg"), [(1, "right"), (3, "left")])
def test_a_knee_that_turns_as_it_flexes_takes_the_joint_centres_timing(seed: int, leg: str) -> None:
    # A tibia that turns about its long axis as the knee flexes reads a lag of its own into the hinge cue (Seel Eq. 2);
    # with the hinge-lean test switched off nothing else tells such a knee from a hinge. The joint-centre cue (Eq. 5)
    # holds on any knee that turns about a centre, so where the two disagree the joint centre's timing is applied.
    # Exact clocks: any lag is the cue's error.
    params = dataclasses.replace(WALKING, axes=dataclasses.replace(WALKING.axes, level_lean_deg=90.0))
    sim = simulate_session(SimConfig(seed=seed, duration_s=90.0, bout_strides=12, knee_3d=2.0, sync_offset_ms=0.0,
                                     clock_drift_ppm=0.0))
    thigh, shank = _leg_streams(sim.streams, leg)
    si = (to_si(thigh), to_si(shank))
    prep = prepare_leg_si(leg, *si, nominal_fs(thigh, si[0][0]), nominal_fs(shank, si[1][0]))
    g1, g2 = fit_gyros(prep, params.axes.fit_cutoff_hz)
    axes = _fitted_axes(prep, g1, g2, params)
    assert not axes.leaning
    clock = clock_model(prep, g1, g2, axes, params.sync, params.axes)
    assert clock.offset_s is not None and abs(clock.offset_s) > 0.01  # the hinge cue alone: over 10 ms off
    assert clock.alternative is not None and abs(clock.alternative.offset_s) < 0.004
    synced = synchronised_leg(leg, thigh, shank, params)
    assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms) < 4.0


@pytest.mark.parametrize(("seed", "leg", "hip_3d", "impact_g", "leaning"),
                         [(1, "left", 1.0, 6.0, False), (8, "right", 1.0, 6.0, False), (18, "left", 0.0, None, False),
                          (6, "left", 0.0, None, True)])
def test_a_running_knee_that_turns_as_it_flexes_keeps_its_clocks(seed: int, leg: str, hip_3d: float,
                                                                  impact_g: float | None, leaning: bool) -> None:
    # Running with 3-D knees, exact clocks. Where the hinge fit does not lean the hinge cue reads ~30 ms (the swing
    # peak would come out ~15 deg low), and a joint-centre cue whose centres are not refitted at each lag, searched
    # around that line, reads 14-29 ms; where it leans the centre cue alone, each window searched around the line of
    # those before, read a line of -10 ms and 260 ppm that way.
    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, activities=("standing",), seed=seed,
                                     n_strides=120, knee_3d=2.0, hip_3d=hip_3d, impact_g=impact_g,
                                     sync_offset_ms=0.0, clock_drift_ppm=0.0))
    thigh, shank = _leg_streams(sim.streams, leg)
    synced = synchronised_leg(leg, thigh, shank, RUNNING)
    assert synced.axes.leaning == leaning
    assert abs(synced.shank_lag_ms or 0.0) < 3.0, synced.shank_lag_ms
    assert abs(synced.shank_drift_ppm or 0.0) < 50.0, synced.shank_drift_ppm
    assert not synced.clock_disagreement


@dataclasses.dataclass(frozen=True)
class _Leg:
    """The straight walk's left leg, 12 ms late, prepared for :func:`_checked_by_centre` on three windows."""

    prep: object
    g1: np.ndarray
    g2: np.ndarray
    axes: object
    windows: list[slice]


@pytest.fixture(scope="module")
def leg(straight) -> _Leg:
    prep, g1, g2, axes = _prepared(*_leg_streams(straight.streams, "left", 0.012))
    edges = np.linspace(0, prep.n, 4).astype(int)
    return _Leg(prep, g1, g2, axes, [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)])


def _checked_with(leg: _Leg, monkeypatch: pytest.MonkeyPatch,
                  lag_of: Callable[[slice, float], LagEstimate | None], hinge: ClockFit,
                  params=WALKING.sync) -> ClockFit:
    """:func:`_checked_by_centre` of the hinge line ``hinge`` with the joint-centre cue replaced by ``lag_of``
    (window, the lag searched around [s])."""
    monkeypatch.setattr("pipeline.sync._centre_lag_of", lambda *_a, **_k: (lag_of, np.ones(leg.prep.n)))
    return _checked_by_centre(leg.prep, leg.g1, leg.g2, leg.axes, params, WALKING.axes, leg.windows, hinge)


def test_a_centre_cue_that_reads_beyond_the_search_range_leaves_the_timing_unknown(
        leg: _Leg, monkeypatch: pytest.MonkeyPatch) -> None:
    # the check of a hinge line: where the joint-centre cue reads 90 ms out (an independent simulator's running leg:
    # hinge 38.7 ms on exact clocks), neither cue is borne out
    def far(_w: slice, _centre: float) -> LagEstimate:
        return LagEstimate(0.0905)

    hinge = ClockFit(0.0387)
    clock = _checked_with(leg, monkeypatch, far, hinge)
    assert clock.offset_s is None and clock.disagreement
    near = dataclasses.replace(WALKING.sync, max_lag_s=0.15)  # within the wide search's range it is a line of its own
    clock = _checked_with(leg, monkeypatch, far, hinge, near)
    assert clock.alternative is not None and clock.alternative.offset_s == pytest.approx(0.0905)
    # a hinge line near the edge of the narrow range (a 75 ms offset read as 67 ms) is left to the wide search
    clock = _checked_with(leg, monkeypatch, far, ClockFit(0.067))
    assert clock.offset_s is None and not clock.disagreement


@pytest.mark.parametrize(("reads_hinge", "expected"), [(True, "hinge"), (False, "unknown")])
def test_centre_windows_that_make_no_line_bear_out_the_hinge_only_where_one_reads_it(
        leg: _Leg, monkeypatch: pytest.MonkeyPatch, reads_hinge: bool, expected: str) -> None:
    # a joint-centre cue whose windows scatter: each reads its own lag whatever it is searched from, but for the
    # first window, which (in one case) reads the hinge line where searched from near it
    w = leg.windows
    rest = {w[0].start: -0.020, w[1].start: 0.015, w[2].start: -0.010}

    def lag_of(win: slice, centre: float) -> LagEstimate:
        if reads_hinge and win.start == 0 and abs(centre - 0.030) < 0.002:
            return LagEstimate(centre)
        return LagEstimate(rest[win.start])

    hinge = ClockFit(0.030)
    clock = _checked_with(leg, monkeypatch, lag_of, hinge)
    if expected == "hinge":
        assert clock == hinge
    else:
        assert clock.offset_s is None and clock.disagreement


def test_a_far_hinge_line_is_checked_where_clocks_usually_are(leg: _Leg, monkeypatch: pytest.MonkeyPatch) -> None:
    # an independent simulator's running leg: the hinge cue read +39 ms where the shank was 26 ms early; searched
    # around the hinge line (-21 .. +99 ms) the joint-centre profile had no clear minimum, searched around 0 it read
    # -27 ms: the centre's line is applied
    def lag_of(_w: slice, centre: float) -> LagEstimate | None:
        return LagEstimate(-0.027) if abs(centre + 0.027) < WALKING.sync.max_lag_s else None

    clock = _checked_with(leg, monkeypatch, lag_of, ClockFit(0.039))
    assert clock.alternative is not None and clock.alternative.offset_s == pytest.approx(-0.027)


def test_a_valley_cut_by_the_end_of_the_hinge_range_is_the_centres_probe(
        leg: _Leg, monkeypatch: pytest.MonkeyPatch) -> None:
    # an independent simulator's walking leg on exact clocks: the hinge cue read -52 ms; around it (-112 .. +8 ms)
    # the joint-centre valley at -3 ms reached the range's end, around zero and from between the two it stood alone
    def lag_of(_w: slice, centre: float) -> LagEstimate | None:
        return LagEstimate(-0.001) if abs(-0.001 - centre) < WALKING.sync.max_lag_s - 0.010 else None

    clock = _checked_with(leg, monkeypatch, lag_of, ClockFit(-0.052))
    assert clock.alternative is not None and clock.alternative.offset_s == pytest.approx(-0.001)


def test_a_second_valley_near_a_far_hinge_line_leaves_the_timing_unknown(
        leg: _Leg, monkeypatch: pytest.MonkeyPatch) -> None:
    # the centre cue has valleys at -5 and +75 ms; around a hinge line of +30 ms (-30 .. +90 ms) it sees both and
    # reads nothing, around zero only the first, and from between the two (12.5 ms) both again: that is one of two
    # hypotheses, not the centre's line
    max_lag = WALKING.sync.max_lag_s

    def lag_of(_w: slice, centre: float) -> LagEstimate | None:
        # a valley 10 ms wide: one whose middle lies up to 10 ms beyond the range still shows as a flank
        seen = [v for v in (-0.005, 0.075) if abs(v - centre) < max_lag + 0.010]
        inside = [v for v in seen if abs(v - centre) < max_lag]
        return LagEstimate(inside[0]) if len(seen) == 1 and inside else None

    clock = _checked_with(leg, monkeypatch, lag_of, ClockFit(0.030))
    assert clock.offset_s is None and clock.disagreement


@pytest.mark.parametrize(("reads_hinge", "expected"), [(True, "hinge"), (False, "unknown")])
def test_a_centre_line_that_runs_away_faster_than_crystals_needs_the_hinge_borne_out(
        leg: _Leg, monkeypatch: pytest.MonkeyPatch, reads_hinge: bool, expected: str) -> None:
    # running at 10 % packet loss: the hinge read -3.8, -3.2, -1.5 ms (true -4.2); two joint-centre windows read 8.0
    # and -3.7 ms, a line of about -390 ppm that two crystals cannot run apart by. The hinge's line stands where
    # another centre window reads it, else (here a line of +400 ppm) the timing is unknown
    w, t_s = leg.windows, leg.prep.t_s
    apart = float(np.mean(t_s[w[2]]) - np.mean(t_s[w[1]]))  # the two windows' times [s]
    reads = {w[0].start: None, w[1].start: 0.008, w[2].start: (-0.0037 if reads_hinge else 0.008 + 0.0004 * apart)}

    def lag_of(win: slice, _centre: float) -> LagEstimate | None:
        lag = reads[win.start]
        return None if lag is None else LagEstimate(lag)

    hinge = ClockFit(-0.003, 2e-5)
    clock = _checked_with(leg, monkeypatch, lag_of, hinge)
    if expected == "hinge":
        assert clock == hinge
    else:
        assert clock.offset_s is None and clock.disagreement


@pytest.mark.parametrize(("seed", "lag_s"), [(3, 0.075), (2, -0.09), (0, -0.09)])
def test_an_offset_beyond_the_narrow_range_is_searched_wide(seed: int, lag_s: float) -> None:
    """Phone-side stamps put 60-90 ms between a thigh and its shank at times (a BLE connection interval and the
    radio's buffering). Beyond ``max_lag_s`` every window's minimum lay at the edge of its range, or the windows
    slid part of the way out (-90 ms read as -54), and the leg went uncorrected into trends with swing peaks 11-17
    deg off; the wide search (``wide_max_lag_s``) finds the offset and the strides are right."""
    sim = simulate_session(SimConfig(seed=seed, duration_s=120.0, bout_strides=12, sync_offset_ms=0.0,
                                     clock_drift_ppm=0.0))
    streams = [dataclasses.replace(s, t_s=s.t_s + lag_s) if (s.leg, s.segment) == ("left", "shank") else s
               for s in sim.streams]
    assert abs(lag_s) > WALKING.sync.max_lag_s
    left = process_session(streams).legs["left"]
    assert left.diagnostics.shank_lag_ms == pytest.approx(1000 * lag_s, abs=3.0)
    truth = [t for t in sim.truth["left"].strides if t.steady]
    errors = [s.peak_swing_flexion_deg - min(truth, key=lambda t: abs(t.t_start_s - s.t_start_s)).peak_swing_flexion_deg
              for s in left.strides if s.quality >= 0.5]
    assert len(errors) >= 40 and max(abs(e) for e in errors) < 6.0


@pytest.mark.parametrize(("cost", "clear"), [
    ([9.0, 4.0, 1.0, 1.5, 6.0, 9.0], True),     # one valley
    ([9.0, 1.2, 3.0, 1.0, 3.0, 9.0], False),    # two valleys within 2.5 x the least
    ([2.0, 1.5, 1.0, 1.4, 6.0, 9.0], False),    # the valley reaches the end of the range
    ([9.0, 1.1, 1.0, 1.2, 1.3, 9.0], True),     # broad, but one valley
    ([9.0, 4.0, np.nan, 1.5, 6.0, 9.0], False),
])
def test_a_lag_profile_is_read_only_from_one_clear_valley(cost: list[float], clear: bool) -> None:
    assert one_valley(np.array(cost), WALKING.sync.centre_depth) == clear


def test_the_centre_profile_reads_the_same_lag_wherever_its_search_starts() -> None:
    """The centres are refitted at every lag: a window reads its lag whether searched around the truth, 0 or the
    far side. Centres fitted once at the start (or moved by one Gauss-Newton step) carry the start's misfit and read
    part of the way from it (a 3-D running knee, 200 Hz: 14-29 ms for a true 0 from a start of 30 ms)."""
    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, activities=("standing",), seed=6, n_strides=120,
                                     knee_3d=1.0, impact_g=6.0, sync_offset_ms=0.0, clock_drift_ppm=0.0))
    prep, g1, g2, _ = _prepared(*_leg_streams(sim.streams, "left", 0.025))
    axes = _fitted_axes(prep, g1, g2, RUNNING)
    a1, a2, gd1, gd2, far = _centre_inputs(prep, g1, g2, RUNNING.sync, RUNNING.axes)
    mid = slice(prep.n // 3, 2 * prep.n // 3)
    reads = [estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, far, prep.fs_hz, mid,
                                   RUNNING.sync.max_lag_s, RUNNING.axes, None, start)[0]
             for start in (0.0, 0.025, 0.05)]
    assert all(lag is not None and abs(lag - 0.025) < 0.003 for lag in reads), reads
    assert max(reads) - min(reads) < 0.001


def test_a_centre_fit_that_misses_the_sensor_reads_no_lag() -> None:
    """A thigh sensor 50 cm from the knee (lever arms x2, a sweep tune seed): the fit's pull towards the knee keeps
    the centres from being found, the Eq. 5 profile is shallow with its least 40-50 ms out, and a line from it took
    over from the hinge's (-13 ms, true -13.9 ms) as +37.6 ms and -328 ppm. Such a window reads no lag: the hinge
    line stands."""
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=3, duration_s=90.0, bout_strides=12,
                                     lever_scale=2.0))
    prep, g1, g2, _ = _prepared(*_leg_streams(sim.streams, "left"))
    axes = _fitted_axes(prep, g1, g2, WALKING)
    a1, a2, gd1, gd2, far = _centre_inputs(prep, g1, g2, WALKING.sync, WALKING.axes)
    third = prep.n // 3
    lag, _ = estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, far, prep.fs_hz,
                                   slice(third, 2 * third), WALKING.sync.max_lag_s, WALKING.axes)
    assert lag is None
    synced = synchronised_leg("left", *_leg_streams(sim.streams, "left"), WALKING)
    assert synced.shank_lag_ms is not None and abs(synced.shank_lag_ms - (-13.9)) < 2.0
