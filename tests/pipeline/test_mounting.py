"""Mounting changes (pipeline/mounting.py): a sensor turned on the limb mid-session keeps the leg out of trends."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.mounting import check_mounting, coherent_step
from pipeline.params import WALKING
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.walking import fit_gyros


def _leg_check(cfg: SimConfig, leg: str = "left"):  # noqa: ANN202
    sim = simulate_session(cfg)
    st = {(s.leg, s.segment): s for s in sim.streams}
    synced = synchronised_leg(leg, st[(leg, "thigh")], st[(leg, "shank")], WALKING)
    fit_gyr = synced.fit_gyr or fit_gyros(synced.prep, WALKING.axes.fit_cutoff_hz)
    return check_mounting(synced.prep, synced.axes, fit_gyr), sim


def test_a_strap_turned_about_the_leg_is_a_mounting_change() -> None:
    """The shank's strap turned 30 deg about the leg half-way: the knee axis in the sensor's frame turns with it."""
    cfg = SimConfig(seed=1, duration_s=120.0, bout_strides=12, remount_segment="shank", remount_deg=30.0,
                    remount_axis="long")
    check, sim = _leg_check(cfg)
    assert check.changed and check.shank_deg > 20.0 and abs(check.at_s - sim.duration_s / 2) < 20.0
    assert not _leg_check(cfg, "right")[0].changed  # the other leg's sensors stayed put
    res = process_session(sim.streams)
    left, right = res.legs["left"], res.legs["right"]
    assert not any("mounting_changed" in s.quality_reasons for s in right.strides)
    # the sitting down after the turn breaks the session's hinge: the leg is processed in two pieces (pipeline.worn),
    # each with its own axes, so its strides are right again; both pieces are too short to vouch for one mounting
    # each (WornParams.trusted_piece_s), so the strides stay out of trends all the same
    assert left.diagnostics.not_worn_s
    truth = [t for t in sim.truth["left"].strides if t.steady]
    errs = [s.peak_swing_flexion_deg - min(truth, key=lambda t: abs(t.t_start_s - s.t_start_s)).peak_swing_flexion_deg
            for s in left.strides]
    assert len(errs) >= 30 and max(abs(e) for e in errs) < 5.0
    assert all(s.quality < 0.5 for s in left.strides)


def test_a_large_turn_names_the_sensor_that_turned() -> None:
    """A shank turned by 90 deg spoils the session's own fit of both axes; the windows on either side still agree
    on the thigh's axis (their lines, whatever the signs) and name the shank."""
    cfg = SimConfig(seed=100, duration_s=90.0, bout_strides=12, remount_segment="shank", remount_deg=90.0)
    check, sim = _leg_check(cfg)
    assert check.changed and check.shank_deg > WALKING.mounting.shank_deg
    assert check.thigh_deg < WALKING.mounting.thigh_deg and abs(check.at_s - sim.duration_s / 2) < 16.0


def test_too_short_to_judge_says_so() -> None:
    check, _ = _leg_check(SimConfig(seed=1, n_strides=8, bout_strides=8))
    assert not check.changed and check.at_s is None and check.thigh_deg is None and check.windows < 4


@pytest.mark.parametrize("cfg", [
    SimConfig(seed=2, duration_s=240.0, bout_strides=12, knee_3d=1.0, hip_3d=1.0,
              activities=("stair_flight", "sit_to_stand", "jump", "step_test")),
    SimConfig(seed=0, duration_s=90.0, bout_strides=12, pattern="fast", bout_pace=(1.0, 0.4), knee_3d=1.0, hip_3d=1.0),
], ids=["3-D knee and hip, stairs, jumps", "pace changing"])
def test_activities_and_a_knee_that_is_no_hinge_are_no_mounting_change(cfg: SimConfig) -> None:
    """The fitted hinge moves with the activity when the knee is no hinge, but those windows interleave."""
    for leg in ("left", "right"):
        check, _ = _leg_check(cfg, leg)
        assert check.windows >= 4 and not check.changed
        assert check.thigh_deg < WALKING.mounting.thigh_deg / 2 and check.shank_deg < WALKING.mounting.shank_deg


def test_the_simulated_remount_turns_only_the_later_readings() -> None:
    base = SimConfig(seed=4, n_strides=16, bout_strides=8)
    a = simulate_session(base)
    b = simulate_session(SimConfig(**{**base.__dict__, "remount_segment": "thigh", "remount_deg": 40.0}))
    for sa, sb in zip(a.streams, b.streams, strict=True):
        later = sa.t_s > a.duration_s / 2 + 0.5  # reported stamps: the clock's offset moves the turn a little
        before = sa.t_s < a.duration_s / 2 - 0.5
        same = np.allclose(sa.gyr, sb.gyr) and np.allclose(sa.acc, sb.acc)
        if (sa.leg, sa.segment) != ("left", "thigh"):
            assert same
            continue
        assert np.allclose(sa.gyr[before], sb.gyr[before]) and not np.allclose(sa.gyr[later], sb.gyr[later])
        # the later readings are the earlier mounting's turned by one rotation of 40 deg, up to the gyro's own bias
        # (1 deg/s, not turned) and noise (0.3 deg/s), far below its swing rates
        fit, _ = Rotation.align_vectors(sb.gyr[later], sa.gyr[later])
        assert np.degrees(fit.magnitude()) == pytest.approx(40.0, abs=1.0)
        info = b.info["sensors"][sb.sensor_id]  # what the session's info says was done: the same turn
        turn = Rotation.from_matrix(np.asarray(info["remount"]["mounting"]) @ np.asarray(info["mounting"]).T)
        assert np.degrees(turn.magnitude()) == pytest.approx(40.0, abs=1e-6)
        assert np.median(np.linalg.norm(sb.gyr[later] - fit.apply(sa.gyr[later]), axis=1)) < 2.0


def test_a_turn_the_axes_barely_show_steps_the_level_in_standing_and_walking_alike() -> None:
    """A thigh sensor turned by 30 deg leaves its fitted hinge within the thigh's threshold (the hip's 3-D motion
    moves it that much), but it turns the joint-plane frames: the level of quiet standing and of the strides'
    mid-stance steps by the same amount, and the leg's strides leave the trends."""
    sim = simulate_session(SimConfig(seed=1, duration_s=90.0, bout_strides=12, remount_segment="thigh",
                                     remount_deg=30.0))
    res = process_session(sim.streams)
    left, right = res.legs["left"].diagnostics.mounting, res.legs["right"].diagnostics.mounting
    assert left.thigh_deg < WALKING.mounting.thigh_deg and left.shank_deg < WALKING.mounting.shank_deg
    assert left.changed and left.level_step_deg > WALKING.mounting.level_step_deg
    assert abs(left.at_s - sim.duration_s / 2) < 10.0
    assert all("mounting_changed" in s.quality_reasons and s.quality < 0.5 for s in res.legs["left"].strides)
    assert not right.changed and right.level_step_deg < 1.0
    assert any("level stepped" in w for w in res.warnings)


_T_STAND = np.array([0.0, 20.0, 40.0, 60.0, 80.0])
_T_STRIDES = np.concatenate([np.arange(5.0, 15.0, 1.0), np.arange(25.0, 35.0, 1.0), np.arange(45.0, 55.0, 1.0),
                             np.arange(65.0, 75.0, 1.0)])


@pytest.mark.parametrize(("stand_step", "stride_step", "shared"), [
    (8.0, 8.0, 8.0),     # a sensor turned at 40 s: both levels move
    (8.0, 0.0, 0.0),     # the patient stands otherwise after 40 s, walks the same
    (0.0, 8.0, 0.0),     # walks otherwise (the knee's minimum before swing), stands the same
    (8.0, -8.0, 0.0),    # opposite steps: no turn of a frame
    (8.0, 4.0, 0.0),     # too different to be one turn (MountingParams.level_agree_deg)
], ids=["both", "standing only", "walking only", "opposite", "disagreeing"])
def test_only_a_step_both_levels_share_counts(stand_step: float, stride_step: float, shared: float) -> None:
    rng = np.random.default_rng(0)
    stand = np.where(_T_STAND >= 40.0, stand_step, 0.0) + rng.normal(0.0, 0.3, _T_STAND.size)
    strides = np.where(_T_STRIDES >= 40.0, stride_step, 0.0) + rng.normal(0.0, 1.0, _T_STRIDES.size)
    step, at_s = coherent_step(_T_STAND, stand, _T_STRIDES, strides)
    if shared:
        assert step == pytest.approx(shared, abs=1.5)
        assert at_s in (40.0, 45.0)  # the standing run or the walking bout the new level starts with
    else:  # a median over a split mixture can fall half-way, so some split may share part of a step, never all
        assert step < WALKING.mounting.level_step_deg


def test_no_split_point_with_both_levels_on_either_side_is_unjudged() -> None:
    assert coherent_step(_T_STAND[:1], np.zeros(1), _T_STRIDES, np.zeros(_T_STRIDES.size)) == (None, None)
    assert coherent_step(_T_STAND, np.zeros(_T_STAND.size), _T_STRIDES[:8], np.zeros(8)) == (None, None)


@pytest.mark.parametrize(("remount_deg", "changed"), [(30.0, True), (0.0, False)])
def test_a_running_thigh_remount_is_seen_by_its_principal_axis(remount_deg: float, changed: bool) -> None:
    """Running with 3-D hip and knee: the refitted hinge wanders by tens of degrees between windows, so a thigh turned
    by 30 deg went unseen (and an unturned one could be flagged); the thigh's principal axis per window moves by the
    turn and by nothing else (``MountingParams.principal_thigh_deg``)."""
    import dataclasses

    from pipeline.params import RUNNING

    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, activities=("standing",), duration_s=90.0,
                                     bout_strides=400, impact_g=6.0, knee_3d=1.0, hip_3d=1.0, seed=0,
                                     remount_segment="thigh" if remount_deg else "none", remount_deg=remount_deg))

    def check(thigh_axis: str):
        params = dataclasses.replace(RUNNING, running=dataclasses.replace(RUNNING.running, thigh_axis=thigh_axis))
        return process_session(sim.streams, activity="running", params=params).legs["left"].diagnostics.mounting

    principal = check("principal")
    assert principal.changed is changed
    assert (principal.thigh_deg > 20.0) if changed else (principal.thigh_deg < 2.0)
    if changed:
        assert not check("hinge").changed  # the free refits' wander hides the turn under their threshold
