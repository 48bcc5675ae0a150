"""Every quality reason the pipeline gives is a documented code (pipeline.reasons)."""

from __future__ import annotations

from pipeline.params import WALKING
from pipeline.reasons import REASONS
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def test_the_quality_parameters_name_documented_codes_only() -> None:
    q = WALKING.quality
    named = {code for code, _ in q.penalties} | set(q.untrusted) | set(q.unmeasured_level)
    assert named <= REASONS.keys(), named - REASONS.keys()


def test_sessions_with_holes_and_running_without_standing_give_documented_codes_only() -> None:
    walking = simulate_session(SimConfig(seed=5, n_strides=24, bout_strides=12, packet_loss=0.05,
                                         loss_model="bursty", packet_samples=20))
    running = simulate_session(SimConfig(pattern="running", fs_hz=200.0, seed=3, n_strides=30, legs=("left",),
                                         bout_strides=30, standing_s=0.5))
    seen: set[str] = set()
    for sim in (walking, running):
        res = process_session(sim.streams, activity=sim.activity)
        for leg in res.legs.values():
            seen |= {r for s in leg.strides for r in s.quality_reasons}
    # the cases reach the data's reasons and the running level's, so the check below covers more than the defaults
    assert {"assumed_level", "bridged_gap", "go_level"} <= seen, seen
    assert seen <= REASONS.keys(), seen - REASONS.keys()

