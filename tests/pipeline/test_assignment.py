"""pipeline.assignment and the session's label checks: swapped thigh/shank and thighs swapped between legs."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.assignment import check_segments, swapped_pairing_better
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def _sim(swap: str):
    return simulate_session(SimConfig(pattern="normal", seed=3, n_strides=20, bout_strides=10,
                                      activities=("standing",), label_swap=swap))


def _rmse(sim, lr) -> float:
    ok = np.isfinite(lr.angle_deg)
    return float(np.sqrt(np.mean((lr.angle_deg[ok] - sim.truth[lr.leg].angle_at(lr.t_s[ok])) ** 2)))


def test_right_labels_are_confirmed() -> None:
    sim = _sim("none")
    by = {(s.leg, s.segment): s for s in sim.streams}
    chk = check_segments(by[("left", "thigh")], by[("left", "shank")])
    assert chk.verdict == "as_labelled" and chk.rate_ratio > 1.5
    res = process_session(sim.streams)
    assert not res.warnings
    assert all(lr.diagnostics.assignment == "as_labelled" for lr in res.legs.values())


@pytest.mark.parametrize("swap, how", [("left_segments", "thigh_shank_exchanged"),
                                       ("thighs", "thighs_exchanged_between_legs")])
def test_swapped_labels_are_corrected_and_warned(swap: str, how: str) -> None:
    sim = _sim(swap)
    res = process_session(sim.streams)
    assert res.warnings
    assert res.legs["left"].diagnostics.assignment == how
    for lr in res.legs.values():
        assert _rmse(sim, lr) < 5.0  # the knee the sensors are on, not an inverted or foreign angle


def test_pairing_rule_needs_a_clear_gain() -> None:
    assert swapped_pairing_better((0.5, 0.6), (0.05, 0.1))
    assert not swapped_pairing_better((0.55, 0.12), (0.5, 0.4))  # a long lever arm, not a swap
