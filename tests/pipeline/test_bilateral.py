"""pipeline.bilateral and the session's alternation check: jumping in place is not gait."""

from __future__ import annotations

import numpy as np

from bench.matching import match_strides
from pipeline.bilateral import OtherLeg, alternates, gait_strides, non_alternating, stride_spans_s
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def test_anti_phase_swings_alternate_and_in_phase_ones_do_not() -> None:
    stride = (10.0, 10.85, 11.1)  # heel strike, own mid-swing, next heel strike
    assert alternates(stride, np.array([9.7, 10.3, 11.4]), [])  # half a cycle off: walking
    assert alternates(stride, np.array([8.65, 9.75, 10.86]), []) is False  # same phase: both legs together
    assert alternates(stride, np.array([]), []) is False  # the other leg stands still
    assert alternates(stride, np.array([]), [(10.2, 10.9)]) is None  # no data to judge


def test_rhythmic_jumps_give_no_strides_and_keep_the_walk() -> None:
    """Twenty seconds of rhythmic jumping between two short bouts: no stride inside the jumps, no impossible angle
    stored, and the walking strides kept: the jumps' in-phase "strides" never vote on the thigh axis's sign (only
    strides that alternate with the other leg do), so they cannot turn the walk's flexion upside down."""
    sim = simulate_session(SimConfig(pattern="normal", seed=1, duration_s=60.0, bout_strides=8,
                                     activities=("jump",), move_reps=8, jump_rest_s=0.0))
    res = process_session(sim.streams)
    jumps = sim.info["non_gait_s"]
    inside = [s for lr in res.legs.values() for s in lr.strides
              if any(a < s.t_end_s and s.t_start_s < b for _, a, b in jumps)]
    assert not inside
    for leg, lr in res.legs.items():
        finite = lr.angle_deg[np.isfinite(lr.angle_deg)]
        assert finite.size and finite.min() >= -15.0 and finite.max() <= 160.0
        steady = [t for t in sim.truth[leg].strides if t.steady]
        pairs = match_strides(lr.strides, steady)
        assert len(pairs) >= 0.95 * len(steady), (leg, len(pairs), len(steady))
        err = [lr.strides[i].peak_swing_flexion_deg - steady[j].peak_swing_flexion_deg for i, j in pairs]
        assert np.max(np.abs(err)) < 5.0


def test_jump_strides_never_vote_on_the_thigh_sign() -> None:
    """Only strides in anti-phase with the other leg's swings are gait (pipeline.bilateral.gait_strides); in-phase
    ones and those of a leg alone are judged as before."""
    t_s = np.arange(0, 10, 0.01)
    strides = [(100, 160, 210), (210, 270, 320), (500, 560, 610)]
    ms = np.array([185, 295, 585])
    other = OtherLeg(np.array([1.3, 2.4, 5.85]))  # anti-phase to the first two, in phase with the third
    assert gait_strides(t_s, strides, ms, other) == strides[:2]
    assert gait_strides(t_s, strides, ms, None) == strides
    assert stride_spans_s(t_s, strides, ms)[0] == (1.0, 1.85, 2.1)


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
