"""Sensors not on the leg (pipeline.worn): a rest in a posture nobody walks in, while the other leg walks."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.params import WALKING
from pipeline.session import process_session
from pipeline.simulate import SimConfig, SimSession, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.types import SessionResult
from pipeline.walking import build_walking_leg_input
from pipeline.worn import handled_spans_s


@cache
def _session(seed: int) -> SimSession:
    """Walking bouts with quiet standing between them and one seated rest (52.6-66.6 s on seed 2)."""
    return simulate_session(SimConfig(seed=seed, duration_s=120.0, bout_strides=12))


def _held(sim: SimSession, leg: str, t_from: tuple[float, float], after_s: float,
          segments: tuple[str, ...] = ("thigh", "shank")) -> list:
    """The session with ``leg``'s sensors on ``segments`` holding, from ``after_s`` on, their mean reading over
    ``t_from`` (plus their noise): kept still in that posture while the rest walks on."""
    rng = np.random.default_rng(1)
    out = []
    for s in sim.streams:
        if s.leg == leg and s.segment in segments:
            src = (s.t_s >= t_from[0]) & (s.t_s <= t_from[1])
            later = s.t_s > after_s
            gyr, acc = s.gyr.copy(), s.acc.copy()
            gyr[later] = 0.3 * rng.standard_normal((int(later.sum()), 3))
            acc[later] = acc[src].mean(axis=0) + 0.05 * rng.standard_normal((int(later.sum()), 3))
            s = dataclasses.replace(s, gyr=gyr, acc=acc)
        out.append(s)
    return out


def _peak_errors(res: SessionResult, sim: SimSession, leg: str, before_s: float) -> list[float]:
    truth = [t for t in sim.truth[leg].strides if t.steady]
    errs = []
    for s in res.legs[leg].strides:
        if s.t_end_s < before_s:
            near = min(truth, key=lambda t: abs(t.t_start_s - s.t_start_s))
            errs.append(s.peak_swing_flexion_deg - near.peak_swing_flexion_deg)
    return errs


@pytest.mark.parametrize("seed", [0, 1])
def test_sensors_taken_off_show_no_angle_and_do_not_bend_the_leg_before(seed: int) -> None:
    """The left leg's sensors are taken off half-way and laid on a table while the person walks on (the simulator's
    ``off_body``): before, the table's "angle" was shown (tens of degrees against the walking knee) and the removal
    entered the hinge fit (the same leg's trace up to 6 deg off before it). Now the table half shows nothing, says
    why, and the strides before it are right."""
    sim = simulate_session(SimConfig(seed=seed, duration_s=90.0, bout_strides=12, off_body="left"))
    off_s = sim.info["sensors"]["L-thigh"]["off_body"]["at_s"]
    res = process_session(sim.streams)
    left = res.legs["left"]
    (t0, t1), = left.diagnostics.not_worn_s
    assert off_s - 3.0 < t0 <= off_s and t1 > sim.duration_s - 1.0
    assert not np.isfinite(left.angle_deg[left.t_s > off_s + 0.5]).any()
    assert any("sensors not on the leg" in w for w in res.warnings)
    assert all(s.t_end_s < off_s for s in left.strides)
    errs = _peak_errors(res, sim, "left", off_s)
    assert len(errs) >= 10 and np.median(np.abs(errs)) < 3.0
    # the piece before the removal is shorter than WornParams.trusted_piece_s: right, but out of trends
    assert all("sensors_handled" in s.quality_reasons and s.quality < 0.5 for s in left.strides)
    ok = np.isfinite(left.angle_deg) & (left.t_s < off_s)
    truth = sim.truth["left"].angle_at(left.t_s[ok])
    assert np.sqrt(np.mean((left.angle_deg[ok] - truth) ** 2)) < 3.0
    assert res.legs["right"].diagnostics.not_worn_s == ()


def test_a_leg_standing_while_the_other_swings_is_worn() -> None:
    """Standing still on one leg while the other swings is a posture a body holds (one-legged exercises): the left
    leg kept in its quiet-standing reading from 70 s on keeps its angle; kept in its seated reading (a seated leg
    while the other walks: not on a body) it does not. The right leg's strides there stay judged against the still
    left leg either way (no one-legged exercise becomes gait)."""
    sim = _session(2)
    standing = process_session(_held(sim, "left", (0.5, 2.5), 70.0))
    assert standing.legs["left"].diagnostics.not_worn_s == ()
    left = standing.legs["left"]
    assert np.isfinite(left.angle_deg[left.t_s > 75.0]).mean() > 0.9
    seated = process_session(_held(sim, "left", (57.0, 63.0), 70.0))
    (t0, t1), = seated.legs["left"].diagnostics.not_worn_s
    assert 60.0 < t0 <= 70.5 and t1 > sim.duration_s - 1.0
    for res in (standing, seated):
        assert all(s.t_end_s < 71.0 for s in res.legs["right"].strides)


@pytest.mark.parametrize("seed", [2, 3])
def test_sitting_and_standing_with_both_legs_is_worn(seed: int) -> None:
    """Both legs rest together (seated, standing between bouts): nothing is cut."""
    res = process_session(_session(seed).streams)
    assert all(lr.diagnostics.not_worn_s == () for lr in res.legs.values())
    assert not any("not on the leg" in w for w in res.warnings)


@pytest.mark.parametrize("legs", [("left", "right"), ("left",)])
def test_all_sensors_taken_off_show_no_angle(legs: tuple[str, ...]) -> None:
    """Every sensor comes off (nothing walks on): taking each off turns it unlike a knee (the hinge test), so each
    leg shows nothing from there on, with or without a second leg."""
    sim = simulate_session(SimConfig(seed=4, duration_s=90.0, bout_strides=12, off_body="all", legs=legs))
    off_s = sim.info["sensors"]["L-thigh"]["off_body"]["at_s"]
    res = process_session(sim.streams)
    assert set(res.legs) == set(legs)
    for lr in res.legs.values():
        (t0, t1), = lr.diagnostics.not_worn_s
        assert off_s - 3.0 < t0 <= off_s and t1 > sim.duration_s - 1.0
        assert not np.isfinite(lr.angle_deg[lr.t_s > off_s]).any()
        assert lr.strides and all(s.t_end_s < off_s for s in lr.strides)


@pytest.mark.parametrize("activities", [("jump", "sit_to_stand", "stair_flight", "step_test"), ()])
def test_a_knee_with_twice_the_typical_3d_motion_turns_like_a_hinge(activities: tuple[str, ...]) -> None:
    """Jumps, sit-to-stand, stairs and walking with twice the typical knee and hip 3-D motion and a varus knee: no
    stretch is taken for sensors being handled."""
    sim = simulate_session(SimConfig(seed=1, duration_s=90.0, bout_strides=12, knee_3d=2.0, hip_3d=2.0,
                                     knee_varus_deg=6.0, activities=activities or ("standing", "turn", "sitting")))
    for leg in ("left", "right"):
        segs = {s.segment: s for s in sim.streams if s.leg == leg}
        synced = synchronised_leg(leg, segs["thigh"], segs["shank"], WALKING)
        data = build_walking_leg_input(synced.prep, WALKING, axes=synced.axes, fit_gyr=synced.fit_gyr)
        assert handled_spans_s(data) == []


def test_sensors_put_back_on_otherwise_learn_their_axes_again() -> None:
    """The left leg's sensors lie on a table from 68 to 84 s (their seated reading held while the right leg walks)
    and go back on turned by 90 deg: each piece is processed on its own, so the strides after the stretch are right,
    and the ones before are not spoilt by the second mounting (both pieces are shorter than
    WornParams.trusted_piece_s, so out of trends). The stretch starts at the sitting down before it: under the whole
    session's axes, a mix of both mountings, that turned unlike a knee too."""
    sim = _session(2)
    turn = Rotation.from_rotvec(np.radians(90.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    held = _held(sim, "left", (57.0, 63.0), 68.0)
    streams = []
    for s, orig in zip(held, sim.streams, strict=True):
        if s.leg == "left":
            back = s.t_s > 84.0
            gyr, acc = s.gyr.copy(), s.acc.copy()
            gyr[back] = orig.gyr[back] @ turn.T
            acc[back] = orig.acc[back] @ turn.T
            s = dataclasses.replace(s, gyr=gyr, acc=acc)
        streams.append(s)
    res = process_session(streams)
    left = res.legs["left"]
    (t0, t1), = left.diagnostics.not_worn_s
    assert 50.0 < t0 <= 68.5 and 84.0 <= t1 < 90.0
    truth = [t for t in sim.truth["left"].strides if t.steady]
    for lo, hi in ((0.0, 68.0), (84.0, 120.0)):
        errs = [st.peak_swing_flexion_deg - min(truth, key=lambda t: abs(t.t_start_s - st.t_start_s))
                .peak_swing_flexion_deg for st in left.strides if lo < st.t_start_s < hi]
        assert len(errs) >= 8 and np.median(np.abs(errs)) < 3.0, (lo, errs)


def test_a_thigh_sensor_fallen_off_while_the_shank_walks_on_shows_nothing() -> None:
    """The left thigh's sensor lies still off the upright from 70 s on (its seated reading held: a strap slipped,
    the sensor on the floor) while the shank's walks on: a walking leg's thigh moves every stride, so from there the
    leg shows nothing, and no stride of it enters trends."""
    sim = _session(2)
    res = process_session(_held(sim, "left", (57.0, 63.0), 70.0, segments=("thigh",)))
    left = res.legs["left"]
    (t0, t1), = left.diagnostics.not_worn_s
    assert 60.0 < t0 <= 70.5 and t1 > sim.duration_s - 1.0
    assert not np.isfinite(left.angle_deg[left.t_s > 70.5]).any()
    assert not [s for s in left.strides if s.t_end_s > 70.5 and s.quality >= 0.5]
    assert len(_peak_errors(res, sim, "left", 68.0)) >= 10


@pytest.mark.parametrize("seed", [1, 2])
def test_a_seated_one_legged_exercise_leaves_the_still_leg_worn(seed: int) -> None:
    """Seated knee extensions between walks, six per knee in turn: the still leg rests seated while the other one
    swings, as it would if its sensors lay on a chair while the person walked, but the swinging thigh lies
    horizontal (pipeline.posture.thigh_upright_at): nobody walks like that. Both legs keep their angle there, and it
    is the knee's."""
    sim = simulate_session(SimConfig(seed=seed, duration_s=120.0, bout_strides=12, activities=("seated_extension",),
                                     move_reps=12))
    res = process_session(sim.streams)
    assert not any("not on the leg" in w for w in res.warnings)
    spans = [(t0, t1) for kind, t0, t1 in sim.info["non_gait_s"] if kind == "seated_extension"]
    assert spans
    for leg, lr in res.legs.items():
        assert lr.diagnostics.not_worn_s == ()
        inside = np.zeros(lr.t_s.size, dtype=bool)
        for t0, t1 in spans:
            inside |= (lr.t_s > t0) & (lr.t_s < t1)
        shown = inside & np.isfinite(lr.angle_deg)
        assert shown.sum() > 0.9 * inside.sum()
        err = lr.angle_deg[shown] - sim.truth[leg].angle_at(lr.t_s[shown])
        assert np.sqrt(np.mean(err**2)) < 5.0


def test_a_pivot_on_one_foot_is_no_handling() -> None:
    """A turn on one foot while standing: the shank turns about the vertical by 20 deg in 0.6 s while the thigh stays
    (the tibia against the femur, as an independent simulator's pivots did), which breaks Seel's hinge as much as
    taking a sensor off: the leg was cut in pieces there and 20 of its 60 strides left the trends. But it leaves
    gravity where it was in both sensors; a removal lays the sensor down. The leg is not cut."""
    sim = _session(2)
    bouts = sim.truth["left"].bouts_s
    t0 = 0.5 * (bouts[3][1] + bouts[4][0]) - 0.3  # mid-way through the standing between the fourth and fifth walk
    streams = []
    for s in sim.streams:
        if (s.leg, s.segment) == ("left", "shank"):
            turn = (s.t_s >= t0) & (s.t_s < t0 + 0.6)
            up = s.acc[(s.t_s > t0 - 1.0) & (s.t_s < t0)].mean(axis=0)
            rate_dps = 20.0 / 0.3 * np.sin(np.pi * (s.t_s[turn] - t0) / 0.6) ** 2  # 20 deg in 0.6 s
            gyr = s.gyr.copy()
            gyr[turn] += rate_dps[:, None] * (up / np.linalg.norm(up))
            s = dataclasses.replace(s, gyr=gyr)
        streams.append(s)
    res = process_session(streams)
    left = res.legs["left"]
    assert left.diagnostics.not_worn_s == () and left.diagnostics.handled_s == ()
    assert len(left.strides) > 50
    # only the walks' own 180 deg turns leave the trends
    assert all(s.quality >= 0.5 for s in left.strides if "turning" not in s.quality_reasons)
    assert sum("turning" in s.quality_reasons for s in left.strides) <= 0.15 * len(left.strides)
