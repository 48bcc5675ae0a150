"""One definition of quiet standing, sitting and lying (pipeline.posture) on simulated sessions with truth."""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.params import RUNNING, WALKING
from pipeline.posture import gait_up_directions, posture_labels, quiet_mask, standing_mask, standing_reference
from pipeline.running import build_running_leg_input
from pipeline.signal_utils import ranges_mask
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


def test_the_shank_stands_near_its_direction_at_the_foot_strikes_in_running() -> None:
    """The shank's mean specific force over a running cycle leans back with the swing (the knee flexes past 90 deg),
    far from its standing direction; at the foot strikes it stands near vertical, as in quiet standing."""
    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, seed=2, n_strides=30, bout_strides=15,
                                     legs=("left",)))
    by = {s.segment: s for s in sim.streams}
    synced = synchronised_leg("left", by["thigh"], by["shank"], RUNNING)
    leg, _ = build_running_leg_input(synced.prep, RUNNING, None)
    prep, j2 = leg.prep, leg.axes.j2
    standing = np.zeros(prep.n, dtype=bool)
    for _, b in sim.truth["left"].bouts_s:
        standing |= (prep.t_s > b + 2.0) & (prep.t_s < b + 3.0)  # the standing after each run
    standing &= quiet_mask(prep, RUNNING.posture)
    assert standing.sum() > 100

    def in_plane_deg(u: np.ndarray, v: np.ndarray) -> float:
        u, v = u - (u @ j2) * j2, v - (v @ j2) * j2
        return float(np.degrees(np.arccos(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)))))

    stand_up = prep.acc_shank_mps2[standing].mean(axis=0)
    cycles = np.asarray(leg.filter_strides)
    cycle_mean = prep.acc_shank_mps2[ranges_mask(prep.n, cycles[:, 0], cycles[:, 1])].mean(axis=0)
    shank_up = gait_up_directions(prep, leg.axes, leg.filter_strides)[1]
    assert in_plane_deg(cycle_mean, stand_up) > 25.0
    assert in_plane_deg(shank_up, stand_up) < 20.0
    assert standing_mask(leg)[standing].mean() > 0.9


def test_without_a_measured_stride_the_shank_takes_its_mean_over_the_strides() -> None:
    """Every stride holding a clipped sample leaves no foot strike to read the shank's gravity at; the shank's
    direction during gait then falls back to its mean specific force, and standing is still found."""
    _, leg = _leg()
    clipped = dataclasses.replace(leg.prep, saturated=np.ones(leg.prep.n, dtype=bool))
    ups = gait_up_directions(clipped, leg.axes, leg.filter_strides)
    assert ups is not None
    arr = np.asarray(leg.filter_strides)
    mean = clipped.acc_shank_mps2[ranges_mask(clipped.n, arr[:, 0], arr[:, 1]) & clipped.valid].mean(axis=0)
    mean -= (mean @ leg.axes.j2) * leg.axes.j2
    np.testing.assert_allclose(ups[1], mean / np.linalg.norm(mean), atol=1e-9)
    assert standing_mask(dataclasses.replace(leg, prep=clipped)).any()
