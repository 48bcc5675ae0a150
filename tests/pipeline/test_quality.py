"""pipeline.quality: penalties, the cap of strides that cannot be vouched for, gap, bout-edge and turn reasons."""

from __future__ import annotations

import numpy as np
import pytest

from bench.matching import match_strides
from pipeline.params import WALKING, FusionParams
from pipeline.policy import _choose, _StrideFlags
from pipeline.quality import edge_reasons, gap_reasons, stride_quality
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def test_untrusted_reasons_stay_below_the_trend_threshold() -> None:
    assert stride_quality(()) == 1.0
    assert stride_quality(("bridged_gap",)) == 0.9
    assert stride_quality(("bridged_gap", "peak_in_gap")) < 0.5
    # an assumed level may enter trends (>= 0.5) but is never scored as vouched for (>= 0.8)
    assert 0.5 <= stride_quality(("assumed_level",)) < 0.8
    worse = ("assumed_level", "bridged_gap", "no_absolute_reference")
    assert stride_quality(worse) < stride_quality(("assumed_level",))


def test_gap_reasons_say_what_fell_in_the_hole() -> None:
    t = np.arange(300) / 100.0
    angle = 30 - 30 * np.cos(2 * np.pi * t)  # peaks at 0.5, 1.5, 2.5 s
    strides = [(0, 20, 100), (100, 120, 200), (200, 220, 299)]
    out = gap_reasons(t, [(1.45, 1.55), (2.05, 2.1)], angle, strides)
    assert out[0] == ()
    assert "peak_in_gap" in out[1] and "bridged_gap" in out[1]
    assert out[2] == ("bridged_gap",)


def test_unsteady_first_stride_of_a_bout_is_marked() -> None:
    strides = [(0, 60, 140), (140, 200, 250), (250, 310, 360), (360, 420, 470), (470, 530, 580)]
    out = edge_reasons(strides, [0] * 5, np.array([200.0, 300.0, 300.0, 300.0, 300.0]))
    assert out[0] == ("bout_edge",) and out[-1] == () and out[2] == ()


def test_a_hole_on_the_swing_rise_makes_the_peak_a_model() -> None:
    t = np.arange(300) / 100.0
    angle = 30 - 30 * np.cos(2 * np.pi * t)  # peaks at 0.5, 1.5, 2.5 s
    strides = [(0, 20, 100), (100, 120, 200), (200, 220, 299)]
    # a fill ending 0.1 s before the peak at 1.5 s; one ending 0.3 s before the peak at 2.5 s
    holes = [(1.2, 1.4), (2.05, 2.15)]
    plain = gap_reasons(t, holes, angle, strides)
    led = gap_reasons(t, holes, angle, strides, peak_lead_s=0.15)
    assert "peak_in_gap" not in plain[1] and "peak_in_gap" in led[1]
    assert led[2] == plain[2] == ("bridged_gap",)  # the rise after 2.15 s is measured
    assert led[0] == ()


def test_long_cubic_bridges_under_the_peak_add_only_the_peak_reason() -> None:
    t = np.arange(300) / 100.0
    angle = 30 - 30 * np.cos(2 * np.pi * t)
    strides = [(0, 20, 100), (100, 120, 200), (200, 220, 299)]
    out = gap_reasons(t, [], angle, strides, bridged_s=[(1.45, 1.57), (2.1, 2.22)], peak_lead_s=0.15)
    # the policy already notes the bridge itself (bridged_gap); here only what it does to the peak
    assert out == [(), ("peak_in_gap",), ()]


def _flags(**set_true: bool) -> _StrideFlags:
    names = ("go_complete", "no_crossing", "drifted", "saturated", "bridged", "mismatch")
    return _StrideFlags(**{n: np.array([set_true.get(n, n == "go_complete")]) for n in names})


@pytest.mark.parametrize("failure", ["no_crossing", "drifted"])
def test_a_cf_fallback_that_disagrees_with_go_is_not_vouched_for(failure: str) -> None:
    """GO failed its own check and the CF replaced it: when the two disagree in shape as well, either may be the wrong
    one, so the stride stays out of trends (agreeing, it keeps the fallback's trend quality)."""
    agree = _choose(_flags(**{failure: True}), 0, True, 100, FusionParams(), WALKING.quality)
    disagree = _choose(_flags(**{failure: True, "mismatch": True}), 0, True, 100, FusionParams(), WALKING.quality)
    assert agree.estimator == disagree.estimator == "cf"
    assert agree.quality >= 0.5 and "go_cf_mismatch" not in agree.reasons
    assert disagree.quality < 0.5 and "go_cf_mismatch" in disagree.reasons


def test_a_short_fill_under_the_peak_leaves_it_measured_a_long_one_does_not() -> None:
    t = np.arange(300) / 100.0
    angle = 30 - 30 * np.cos(2 * np.pi * t)
    strides = [(0, 20, 100), (100, 120, 200), (200, 220, 299)]
    short = WALKING.quality.filled_peak_s
    # one lost packet's hole on the peak at 1.5 s; a hole twice as long on the peak at 2.5 s
    holes = [(1.45, 1.45 + short - 0.01), (2.35, 2.35 + 2 * short)]
    out = gap_reasons(t, holes, angle, strides, peak_lead_s=0.15, short_fill_s=short)
    assert out[1] == ("bridged_gap",)
    assert "peak_in_gap" in out[2] and "bridged_gap" in out[2]
    assert "peak_in_gap" in gap_reasons(t, holes, angle, strides, peak_lead_s=0.15)[1]  # every fill counts without


def test_a_fill_longer_than_half_a_stride_keeps_the_stride_out_of_trends() -> None:
    """A hole longer than ``trusted_fill_s`` between a stride's minimum and its peak leaves both measured, yet a whole
    stance phase may be the neighbours': the stride is counted (``long_gap``) but not vouched for; a shorter one
    there keeps trend quality."""
    t = np.arange(600) / 100.0
    angle = 30 - 30 * np.cos(np.pi * t)  # 2 s strides: minima at 0, 2, 4 s, peaks at 1, 3, 5 s
    strides = [(0, 25, 200), (200, 225, 400), (400, 425, 599)]
    trusted = WALKING.quality.trusted_fill_s
    # after toe-off, ending before the swing-flexion rise that leads to the peak
    holes = [(0.35, 0.35 + trusted - 0.2), (2.3, 2.3 + trusted + 0.03)]
    out = gap_reasons(t, holes, angle, strides, peak_lead_s=0.15, short_fill_s=WALKING.quality.filled_peak_s,
                      trusted_fill_s=trusted)
    assert out[0] == ("bridged_gap",)
    assert out[1] == ("bridged_gap", "long_gap")
    assert out[2] == ()
    assert stride_quality(out[0]) >= 0.5 > stride_quality(out[1])


def test_strides_of_a_turn_stay_out_of_trends_straight_ones_do_not() -> None:
    sim = simulate_session(SimConfig(seed=1, duration_s=90.0, turns_per_bout=3, turn_strides=1.0,
                                     turn_angle_deg=90.0))
    res = process_session(sim.streams, activity=sim.activity)
    flagged = straight_flagged = turning_true = turning_found = 0
    for leg, truth in sim.truth.items():
        strides = res.legs[leg].strides
        for i, j in match_strides(strides, truth.strides):
            s, t = strides[i], truth.strides[j]
            turning = "turning" in s.quality_reasons
            flagged += turning
            straight_flagged += turning and not t.turning
            turning_true += t.turning
            turning_found += turning and t.turning
            if turning:
                assert s.quality < 0.5
    assert straight_flagged == 0
    assert turning_true >= 6 and turning_found >= 0.8 * turning_true, (turning_found, turning_true)
