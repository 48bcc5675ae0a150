"""One definition of quiet standing, sitting and lying (pipeline.posture) on simulated sessions with truth."""

from __future__ import annotations

import numpy as np

from pipeline.params import WALKING
from pipeline.posture import posture_labels, standing_reference
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.walking import build_walking_leg_input


def _leg(**kw):
    sim = simulate_session(SimConfig(**{"pattern": "normal", "seed": 7, "duration_s": 80.0, "bout_strides": 12,
                                        "legs": ("left",), **kw}))
    by = {s.segment: s for s in sim.streams}
    synced = synchronised_leg("left", by["thigh"], by["shank"], WALKING)
    return sim, build_walking_leg_input(synced.prep, WALKING, axes=synced.axes, fit_gyr=synced.fit_gyr)


def test_sitting_and_standing_are_told_apart_and_the_zero_uses_standing_only() -> None:
    sim, leg = _leg(activities=("sitting",))
    labels = posture_labels(leg)
    sits = [(a, b) for kind, a, b in sim.info["non_gait_s"] if kind == "sit"]
    seated = np.zeros(leg.prep.n, dtype=bool)
    for a, b in sits:  # the middle of each seated period, clear of the transitions
        seated |= (leg.prep.t_s > a + 3.0) & (leg.prep.t_s < b - 3.0)
    assert seated.any()
    assert np.mean(labels[seated] == "sitting") > 0.9
    assert not np.any(labels[seated] == "standing")
    assert np.any(labels == "standing")  # the quiet standing before the first bout
    assert standing_reference(leg, leg.acc_angle_deg) is not None


def test_without_quiet_standing_there_is_no_zero() -> None:
    _, leg = _leg(activities=("turn",), standing_s=0.5, bout_strides=1000)
    assert not np.any(posture_labels(leg) == "standing")
    assert standing_reference(leg, leg.acc_angle_deg) is None
