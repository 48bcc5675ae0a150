"""pipeline.prepare: units, common grid, gap handling."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.params import WALKING, PrepareParams
from pipeline.prepare import (
    EDGE_TOL_S,
    MAX_BRIDGE_S,
    PreparedLeg,
    _mask_intervals,
    periodic_fill,
    prepare_leg,
    prepare_leg_si,
    saturation_mask,
    to_si,
)
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.types import RawSensorStream


def _stream(seg: str, t: np.ndarray, gyr_dps: np.ndarray, acc_mps2: np.ndarray, fs: float,
            gyro_unit: str = "deg/s", acc_unit: str = "m/s2") -> RawSensorStream:
    gyr = np.deg2rad(gyr_dps) if gyro_unit == "rad/s" else gyr_dps
    acc = acc_mps2 / 9.80665 if acc_unit == "g" else acc_mps2
    return RawSensorStream(sensor_id=seg, leg="left", segment=seg, fs_hz=fs, t_s=t, gyr=gyr, acc=acc,
                           gyro_unit=gyro_unit, acc_unit=acc_unit)


def _signals(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gyr = np.column_stack([100 * np.sin(2 * np.pi * t), 50 * np.cos(2 * np.pi * 0.5 * t), 10 * t])
    acc = np.column_stack([np.sin(t), np.cos(t), 9.81 + 0 * t])
    return gyr, acc


def test_units_are_converted_to_si() -> None:
    t = np.arange(0, 5, 0.01)
    g, a = _signals(t)
    p_deg = prepare_leg("left", _stream("thigh", t, g, a, 100), _stream("shank", t, g, a, 100))
    p_rad = prepare_leg("left", _stream("thigh", t, g, a, 100, "rad/s", "g"),
                        _stream("shank", t, g, a, 100, "rad/s", "g"))
    np.testing.assert_allclose(p_deg.gyr_thigh_rps, np.deg2rad(g), atol=1e-9)
    np.testing.assert_allclose(p_rad.gyr_shank_rps, p_deg.gyr_shank_rps, atol=1e-9)
    np.testing.assert_allclose(p_rad.acc_shank_mps2, p_deg.acc_shank_mps2, atol=1e-9)


def test_different_rates_and_offsets_share_one_uniform_grid() -> None:
    t1 = 0.013 + np.arange(0, 6, 1 / 50)
    t2 = 0.004 + np.arange(0, 6, 1 / 100)
    g1, a1 = _signals(t1)
    g2, a2 = _signals(t2)
    p = prepare_leg("left", _stream("thigh", t1, g1, a1, 50), _stream("shank", t2, g2, a2, 100))
    assert p.fs_hz == 100
    np.testing.assert_allclose(np.diff(p.t_s), 0.01, atol=1e-12)
    assert p.t_s[0] >= t1[0] and p.t_s[-1] <= t2[-1]
    g_true, _ = _signals(p.t_s)
    # linear interpolation of the 50 Hz thigh: small error on a 1 Hz, 100 dps sine
    assert np.max(np.abs(np.rad2deg(p.gyr_thigh_rps[:, 0]) - g_true[:, 0])) < 1.0
    assert p.valid.all()


def test_short_gaps_are_bridged_and_long_gaps_masked() -> None:
    t = np.arange(0, 10, 0.01)
    drop = np.zeros(t.size, dtype=bool)
    drop[200:210] = True  # 110 ms: bridged
    drop[500:590] = True  # 0.9 s: masked
    g, a = _signals(t)
    thigh = _stream("thigh", t[~drop], g[~drop], a[~drop], 100)
    p = prepare_leg("left", thigh, _stream("shank", t, g, a, 100))
    assert MAX_BRIDGE_S > 11 * 0.01
    assert len(p.gaps_s) == 1
    a_s, b_s = p.gaps_s[0]
    assert a_s == pytest.approx(t[499]) and b_s == pytest.approx(t[590])
    inside = (p.t_s > a_s + EDGE_TOL_S) & (p.t_s < b_s - EDGE_TOL_S)
    assert not p.valid[inside].any()
    assert p.valid[~inside].all()
    assert (~p.valid).sum() == 90  # exactly the dropped samples: the received ones on both edges are kept
    assert p.bridged_gaps == 1


def test_no_overlap_is_an_error() -> None:
    t = np.arange(0, 2, 0.01)
    g, a = _signals(t)
    with pytest.raises(ValueError, match="overlap"):
        prepare_leg("left", _stream("thigh", t, g, a, 100), _stream("shank", t + 5, g, a, 100))


def test_holes_in_periodic_gait_are_filled_from_the_neighbouring_strides() -> None:
    t = np.arange(0, 12, 0.01)
    ph = 2 * np.pi * t / 1.1  # a 1.1 s stride with a swing peak: several harmonics, like a shank rate
    g = np.column_stack([300 * np.sin(ph) ** 3 + 80 * np.sin(2 * ph), 40 * np.cos(ph), 20 * np.sin(3 * ph)])
    a = np.column_stack([np.sin(ph), np.cos(ph), 9.81 + np.sin(2 * ph)])
    drop = np.zeros(t.size, dtype=bool)
    drop[600:640] = True  # 0.41 s: longer than the cubic bridge, inside periodic gait
    thigh = _stream("thigh", t[~drop], g[~drop], a[~drop], 100)
    p = prepare_leg("left", thigh, _stream("shank", t, g, a, 100))
    assert p.valid.all() and len(p.filled_s) == 1 and not p.gaps_s
    err = np.rad2deg(p.gyr_thigh_rps[595:645]) - g[595:645]
    assert np.max(np.abs(err)) < 5.0  # of a 300 deg/s swing


def _gait(phase: np.ndarray) -> np.ndarray:
    """A shank-like rate [deg/s] with a swing peak: several harmonics of the stride phase ``phase`` [rad]."""
    return np.column_stack([300 * np.sin(phase) ** 3 + 80 * np.sin(2 * phase), 40 * np.cos(phase),
                            20 * np.sin(3 * phase)])


def _thigh_holes(t: np.ndarray, g: np.ndarray, drop: np.ndarray, params: PrepareParams = WALKING.prepare,
                 thigh_t: np.ndarray | None = None) -> PreparedLeg:
    """A leg at 100 Hz whose thigh (stamps ``thigh_t``, default ``t``) lost the samples ``drop``; both sensors read
    the rate ``g`` [deg/s] and gravity."""
    a = np.column_stack([0 * t, 0 * t, 9.81 + 0 * t])
    stamps = t if thigh_t is None else thigh_t
    return prepare_leg("left", _stream("thigh", stamps[~drop], g[~drop], a[~drop], 100),
                       _stream("shank", t, g, a, 100), params=params)


def _fill_error(t: np.ndarray, g: np.ndarray, drop: np.ndarray, params: PrepareParams = WALKING.prepare
                ) -> tuple[np.ndarray, list]:
    """Gyro error [deg/s] of the thigh's filled samples where ``drop`` removed them, and its masked gaps."""
    p = _thigh_holes(t, g, drop, params)
    return np.rad2deg(p.gyr_thigh_rps[drop]) - g[drop], p.thigh_gaps_s


def test_a_hole_at_a_bouts_end_is_filled_from_the_stride_before_it() -> None:
    """Gait, then standing still: the context after the hole repeats nothing, the one before it does."""
    t = np.arange(0, 12, 0.01)
    walking = t < 7.0
    g = np.where(walking[:, None], _gait(2 * np.pi * t / 1.1), 0.5)
    drop = (t > 6.55) & (t < 6.75)  # 0.2 s at the last stride's end, 0.25 s before the still part
    err, gaps = _fill_error(t, g, drop)
    assert not gaps
    assert np.max(np.abs(err)) < 10.0  # of a 300 deg/s swing


def test_a_hole_longer_than_half_a_stride_at_a_bouts_end_stays_masked() -> None:
    """Gait on one side only: a hole that long may hold the bout's end, so no gait is written into it; inside gait
    the same hole is filled."""
    t = np.arange(0, 12, 0.01)
    walking = t < 7.0
    g = np.where(walking[:, None], _gait(2 * np.pi * t / 1.1), 0.5)
    long_s = WALKING.prepare.one_sided_fill_s + 0.1
    assert long_s < WALKING.prepare.periodic_bridge_s
    at_end = (t > 6.9 - long_s) & (t < 6.9)
    _, gaps = _fill_error(t, g, at_end)
    assert len(gaps) == 1
    inside = (t > 4.0) & (t < 4.0 + long_s)
    err, gaps = _fill_error(t, _gait(2 * np.pi * t / 1.1), inside)
    assert not gaps
    assert np.max(np.abs(err)) < 10.0


def test_a_hole_whose_neighbours_lost_the_same_phase_takes_the_stride_two_periods_away() -> None:
    t = np.arange(0, 14, 0.01)
    g = _gait(2 * np.pi * t / 1.1)
    drop = np.zeros(t.size, dtype=bool)
    for c in (5.2, 6.3, 7.4):  # the same phase in three consecutive strides
        drop |= (t > c) & (t < c + 0.2)
    err, gaps = _fill_error(t, g, drop)
    assert not gaps
    assert np.max(np.abs(err)) < 10.0


def test_the_template_is_warped_to_the_strides_own_timing() -> None:
    """Strides lengthen by 3 % each: the stride before is shorter and the one after longer than the holed one, so a
    template at one lag is out of phase at one edge or both; aligned at either edge it follows the stride."""
    t = np.arange(0, 14, 0.01)
    period = 1.0 * 1.03 ** (t / 1.05)
    g = _gait(2 * np.pi * np.cumsum(0.01 / period))
    drop = (t > 7.0) & (t < 7.35)
    warped, gaps = _fill_error(t, g, drop)
    fixed, _ = _fill_error(t, g, drop, dataclasses.replace(WALKING.prepare, periodic_max_warp=0.0))
    assert not gaps
    assert np.sqrt(np.mean(warped ** 2)) < 0.5 * np.sqrt(np.mean(fixed ** 2))


def test_holes_without_periodic_context_stay_masked() -> None:
    t = np.arange(0, 12, 0.01)
    rng = np.random.default_rng(0)
    g = np.cumsum(rng.normal(0, 5, (t.size, 3)), axis=0)  # a random walk repeats nothing
    a = np.column_stack([0 * t, 0 * t, 9.81 + 0 * t])
    drop = np.zeros(t.size, dtype=bool)
    drop[600:640] = True
    p = prepare_leg("left", _stream("thigh", t[~drop], g[~drop], a[~drop], 100), _stream("shank", t, g, a, 100))
    assert len(p.gaps_s) == 1 and not p.filled_s


def test_grid_sample_on_a_gap_edge_is_kept_whatever_its_last_bit() -> None:
    """The grid is anchored on received stamps, so its samples fall on a gap's edges; rounding must not decide."""
    edge0, edge1 = 1.0, 1.5
    for eps in (-4e-16, 0.0, 4e-16):
        t_grid = np.array([0.9, edge0 + eps, 1.1, 1.4, edge1 + eps, 1.6])
        assert _mask_intervals(t_grid, [(edge0, edge1)]).tolist() == [False, False, True, True, False, False]


def test_lossy_session_is_stable_under_last_bit_noise() -> None:
    """1e-13 relative noise on the gyros (what another CPU's SIMD kernels give) moves no stride and no masked sample:
    this session's clock correction puts grid samples on gap edges (``EDGE_TOL_S``)."""
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=128.0, seed=907, duration_s=60.0, packet_loss=0.03,
                                     packet_samples=20))
    base = process_session(sim.streams, "walking")
    rng = np.random.default_rng(0)
    for _ in range(3):
        noisy = [dataclasses.replace(s, gyr=s.gyr * (1 + 1e-13 * rng.standard_normal(s.gyr.shape)))
                 for s in sim.streams]
        res = process_session(noisy, "walking")
        for leg, lr in base.legs.items():
            other = res.legs[leg]
            assert len(other.strides) == len(lr.strides)
            assert np.array_equal(np.isfinite(other.angle_deg), np.isfinite(lr.angle_deg))
            peaks = np.array([s.peak_swing_flexion_deg for s in lr.strides])
            assert np.abs(np.array([s.peak_swing_flexion_deg for s in other.strides]) - peaks).max() < 1e-8


def test_a_re_stamped_shank_keeps_the_first_grid_cut_to_its_span() -> None:
    """The clock correction re-stamps the shank only: the thigh's channels on the first pass's grid are kept, and
    the grid loses just the samples the moved shank no longer covers (its phase stays)."""
    t = np.arange(0, 20, 0.01)
    g, a = _signals(t)
    si = to_si(_stream("thigh", t, g, a, 100)), to_si(_stream("shank", t + 0.0005, g, a, 100))
    first = prepare_leg_si("left", *si, 100.0, 100.0)
    assert first.t_s[0] == 0.0005
    same = prepare_leg_si("left", *si, 100.0, 100.0, shank_shift_s=-0.0004, reuse=first)
    assert same.t_s is first.t_s and same.gyr_thigh_rps is first.gyr_thigh_rps
    later = prepare_leg_si("left", *si, 100.0, 100.0, shank_shift_s=0.003, reuse=first)
    np.testing.assert_array_equal(later.t_s, first.t_s[1:])  # the first grid sample is before the moved shank
    np.testing.assert_array_equal(later.gyr_thigh_rps, first.gyr_thigh_rps[1:])
    np.testing.assert_array_equal(later.acc_thigh_mps2, first.acc_thigh_mps2[1:])
    assert later.t0_s == later.t_s[0] and later.n == first.n - 1
    # and the shank is the re-stamped one: its samples of g(t), stamped t + 0.0005, now sit at t + 0.0035
    expected = np.deg2rad(100 * np.sin(2 * np.pi * (later.t_s - 0.0035)))
    np.testing.assert_allclose(later.gyr_shank_rps[:, 0], expected, atol=1e-3)


def test_a_short_hole_in_gait_takes_the_neighbouring_strides_over_the_cubic() -> None:
    """0.11 s on the swing rise: the cubic bridge cuts the rate's peak, the neighbouring strides hold it."""
    t = np.arange(0, 12, 0.01)
    g = _gait(2 * np.pi * t / 1.1)
    drop = (t > 6.2) & (t < 6.3)
    p = _thigh_holes(t, g, drop)
    assert p.valid.all() and p.filled_s and not p.bridged_s
    filled, _ = _fill_error(t, g, drop)
    cubic, _ = _fill_error(t, g, drop, dataclasses.replace(WALKING.prepare, periodic_bridge_s=0.0))
    assert np.max(np.abs(filled)) < 0.3 * np.max(np.abs(cubic))


def test_a_fill_whose_edges_disagree_by_more_than_its_length_is_not_folded_back() -> None:
    """A short hole near the grid's end in a stride whose timing wobbles: the edge shifts can differ by more than
    the hole is long, which would run the template backwards (and past the grid's end)."""
    fs, n = 100.0, 500
    t = np.arange(n) / fs
    sig = np.sin(2 * np.pi * (t / 1.59 + 0.08 * np.sin(2 * np.pi * t / 3.0))) ** 3
    x = np.tile(sig[:, None], (1, 6))
    out, filled, kept = periodic_fill(t, x, [], fs, bridged=[(3.34, 3.44)])
    assert not kept
    inside = (t > 3.34) & (t < 3.44)
    assert np.all(np.isfinite(out)) and np.max(np.abs(out[inside])) <= 1.0 + 1e-9
    np.testing.assert_array_equal(out[~inside], x[~inside])


def test_two_holes_with_one_received_sample_between_are_filled_as_one() -> None:
    """The lone sample between them is off the grid: the grid samples next to it are interpolated across both holes,
    so neither hole has a measured edge there; filled as one hole, both follow the signal."""
    t = np.arange(0, 10, 0.01)
    g = _gait(2 * np.pi * t / 1.1)
    stamps = t - 0.003  # the thigh's stamps 3 ms off the shank's grid
    drop = np.zeros(t.size, dtype=bool)
    drop[500:511] = True  # 0.12 s
    drop[512:540] = True  # 0.29 s, sample 511 alone received between
    p = _thigh_holes(t, g, drop, thigh_t=stamps)
    assert not p.gaps_s
    # the grid samples next to the lone sample were overwritten with the rest: none of them counts as measured
    first, last = stamps[499], stamps[540]
    assert not p.measured()[(p.t_s > first) & (p.t_s < last)].any()
    assert p.measured()[(p.t_s > first - 0.5) & (p.t_s < first)].all()
    truth = _gait(2 * np.pi * (p.t_s + 0.003) / 1.1)
    err = np.rad2deg(p.gyr_thigh_rps + p.gyr_bias_thigh_rps) - truth
    assert np.max(np.abs(err[(p.t_s > 4.9) & (p.t_s < 5.5)])) < 3.0  # of a 300 deg/s swing


def test_measured_samples_leave_out_the_filled_holes() -> None:
    t = np.arange(0, 12, 0.01)
    g = _gait(2 * np.pi * t / 1.1)
    drop = (t > 6.0) & (t < 6.3)
    p = _thigh_holes(t, g, drop)
    assert p.valid.all() and p.filled_s
    inside = _mask_intervals(p.t_s, p.filled_s)
    np.testing.assert_array_equal(p.measured(), p.valid & ~inside)
    assert inside.sum() == drop.sum()


def test_a_grid_sample_overwritten_between_two_holes_is_not_measured() -> None:
    """Two received samples between two holes, off the grid, with one grid sample between them: that sample is
    interpolated across both holes, so they are filled as one (`_adjacent_holes`) and it is overwritten with them;
    it must not count as measured (the clock cues and the axis fit read only measured samples)."""
    t = np.arange(0, 10, 0.01)
    g = _gait(2 * np.pi * t / 1.1)
    stamps = t - 0.003
    drop = np.zeros(t.size, dtype=bool)
    drop[500:511] = True
    drop[513:540] = True  # samples 511 and 512 received between, grid sample 5.11 s between them
    p = _thigh_holes(t, g, drop, thigh_t=stamps)
    assert not p.gaps_s
    between = np.flatnonzero(np.isclose(p.t_s, 5.11))
    assert between.size == 1 and not p.measured()[between[0]]


def test_a_broad_unclipped_peak_is_no_saturation_a_clipped_one_is() -> None:
    """At 200 Hz a smooth swing peak keeps three samples within 0.1 % of its top; a clipped sensor repeats its
    full-scale value exactly."""
    t = np.arange(400) / 200.0
    swing = np.zeros((t.size, 3))
    swing[:, 1] = np.deg2rad(400.0) * np.sin(2 * np.pi * 0.9 * t)  # a broad peak, no noise (the hardest case)
    assert not saturation_mask(swing).any()
    clipped = swing.copy()
    clipped[:, 1] = np.clip(clipped[:, 1], -np.deg2rad(380.0), np.deg2rad(380.0))
    mask = saturation_mask(clipped)
    assert mask.any() and mask[np.abs(clipped[:, 1]) >= np.deg2rad(380.0)].all()
