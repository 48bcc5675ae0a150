"""pipeline.bilateral and the session's alternation check: jumping in place is not gait."""

from __future__ import annotations

import numpy as np

from pipeline.bilateral import alternates, non_alternating
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def test_anti_phase_swings_alternate_and_in_phase_ones_do_not() -> None:
    stride = (10.0, 10.85, 11.1)  # heel strike, own mid-swing, next heel strike
    assert alternates(stride, np.array([9.7, 10.3, 11.4]), [])  # half a cycle off: walking
    assert alternates(stride, np.array([8.65, 9.75, 10.86]), []) is False  # same phase: both legs together
    assert alternates(stride, np.array([]), []) is False  # the other leg stands still
    assert alternates(stride, np.array([]), [(10.2, 10.9)]) is None  # no data to judge


def test_rhythmic_jumps_give_no_strides() -> None:
    """Twenty seconds of rhythmic jumping between two short bouts: no stride inside the jumps and no impossible
    angle stored. The walking strides of such a session are lost too (the thigh axis sign is voted per leg over
    every stride-like cycle, before the legs are compared, and the jumps outvote the walk), which the closing
    assertion pins until the vote moves after the alternation check."""
    sim = simulate_session(SimConfig(pattern="normal", seed=1, duration_s=60.0, bout_strides=8,
                                     activities=("jump",), move_reps=8, jump_rest_s=0.0))
    res = process_session(sim.streams)
    jumps = sim.info["non_gait_s"]
    inside = [s for lr in res.legs.values() for s in lr.strides
              if any(a < s.t_end_s and s.t_start_s < b for _, a, b in jumps)]
    assert not inside
    for lr in res.legs.values():
        finite = lr.angle_deg[np.isfinite(lr.angle_deg)]
        assert finite.size and finite.min() >= -15.0 and finite.max() <= 160.0
    assert all(len(lr.strides) < 5 for lr in res.legs.values())


def test_short_jump_block_keeps_the_walking_strides() -> None:
    """Three jumps with rests between bouts: the alternation check and the gait-only axis sign keep every
    walking bout's strides and none inside the jumps."""
    sim = simulate_session(SimConfig(pattern="normal", seed=1, duration_s=60.0, bout_strides=8,
                                     activities=("jump",)))
    res = process_session(sim.streams)
    jumps = sim.info["non_gait_s"]
    inside = [s for lr in res.legs.values() for s in lr.strides
              if any(a < s.t_end_s and s.t_start_s < b for _, a, b in jumps)]
    assert not inside
    assert all(len(lr.strides) > 5 for lr in res.legs.values())


def test_non_alternating_lists_only_judged_failures() -> None:
    spans = [(0.0, 0.85, 1.1), (1.1, 1.95, 2.2)]
    assert non_alternating(spans, np.array([0.3, 1.4, 2.5]), []) == []
    assert non_alternating(spans, np.array([0.85, 1.95]), []) == [0, 1]
