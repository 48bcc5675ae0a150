"""pipeline.assignment and the session's label checks: swapped thigh/shank and thighs swapped between legs."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from bench.matching import match_strides
from pipeline.assignment import (
    centre_heights_m,
    check_segments,
    segments_by_centre,
    side_verdict,
    swapped_pairing_better,
)
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


def _sim_3d(swap: str, hip_3d: float = 1.0, seed: int = 5, **kw):
    """A walker with typical pelvis and hip motion (the frontal plane the side check reads). Seed 5: both figures of
    the weight shift clear the floor on both legs (they do on about half of such simulated sessions)."""
    return simulate_session(SimConfig(pattern="normal", seed=seed, n_strides=20, bout_strides=10,
                                      activities=("standing",), hip_3d=hip_3d, label_swap=swap, **kw))


def test_weight_shift_is_mirrored_between_the_legs() -> None:
    res = process_session(_sim_3d("none").streams)
    shift = {leg: lr.diagnostics.weight_shift_dps for leg, lr in res.legs.items()}
    assert min(shift["left"]) >= 2.0 and max(shift["right"]) <= -2.0
    assert side_verdict(shift["left"], shift["right"]) == "as_labelled"
    assert not any("swapped" in w for w in res.warnings)
    assert not any("side_in_doubt" in s.quality_reasons for lr in res.legs.values() for s in lr.strides)


def test_left_right_labels_swapped_keep_every_stride_out_of_trends() -> None:
    res = process_session(_sim_3d("legs").streams)
    assert any("left and right labels look swapped" in w for w in res.warnings)
    strides = [s for lr in res.legs.values() for s in lr.strides]
    assert len(strides) > 20
    assert all("side_in_doubt" in s.quality_reasons and s.quality < 0.5 for s in strides)


def test_an_exercise_without_gait_keeps_its_labels() -> None:
    """A step test alone (no walking) moves the thigh faster than the shank: the swing-rate rule reads the labels as
    exchanged, but no gait stride confirms it, so they stand (warned). Nor is it gait as labelled: no stride is kept,
    and without gait the knee axes and zero are unanchored, so no trace is shown either."""
    import dataclasses

    sim = simulate_session(SimConfig(seed=1, n_strides=12, bout_strides=6, activities=("step_test",), move_reps=10))
    _, t0, t1 = sim.info["non_gait_s"][0]

    def cut(s):  # noqa: ANN001, ANN202
        m = (s.t_s >= t0 - 3) & (s.t_s < t1 + 1)
        return dataclasses.replace(s, t_s=s.t_s[m] - (t0 - 3), gyr=s.gyr[m], acc=s.acc[m])

    streams = [cut(s) for s in sim.streams]
    by_leg = {leg: {s.segment: s for s in streams if s.leg == leg} for leg in ("left", "right")}
    assert all(check_segments(d["thigh"], d["shank"]).verdict == "swapped" for d in by_leg.values())
    res = process_session(streams)
    assert all(lr.diagnostics.assignment == "as_labelled" and not lr.strides for lr in res.legs.values())
    assert not any("labels exchanged" in w for w in res.warnings)
    assert sum("labels kept as given" in w for w in res.warnings) == 2
    assert all(lr.diagnostics.trace_withheld == "no_gait" and np.isnan(lr.angle_deg).all()
               for lr in res.legs.values())


def test_legs_without_gait_strides_are_not_judged_by_their_weight_shift() -> None:
    """The weight-shift cue is a property of gait strides: where the drops left a leg fewer than
    ``shift_min_strides`` of them (a session of stair flights), mirrored shifts say nothing about the labels."""
    import dataclasses

    from pipeline.params import WALKING
    from pipeline.session import _check_sides

    res = process_session(_sim_3d("legs").streams)
    few = WALKING.assignment.shift_min_strides - 1
    legs = {leg: dataclasses.replace(lr, strides=lr.strides[:few]) for leg, lr in res.legs.items()}
    warnings: list[str] = []
    assert _check_sides(legs, WALKING.assignment, WALKING.quality, warnings) == legs and not warnings
    legs = {leg: dataclasses.replace(lr, strides=lr.strides[:few + 1]) for leg, lr in res.legs.items()}
    flagged = _check_sides(legs, WALKING.assignment, WALKING.quality, warnings)
    assert warnings and all("side_in_doubt" in s.quality_reasons for lr in flagged.values() for s in lr.strides)


@pytest.mark.parametrize("cfg", [
    SimConfig(pattern="normal", seed=5, n_strides=20, bout_strides=10, activities=("standing",)),
    SimConfig(pattern="normal", seed=5, n_strides=20, bout_strides=10, activities=("standing",), thigh_sta_deg=-10.0),
    SimConfig(pattern="normal", seed=201, duration_s=90.0, gyro_bias_dps=10.0)],
    ids=["planar", "planar_skin_turning_inwards", "planar_gyro_bias_no_rest_removes"])
def test_without_frontal_motion_right_labels_are_never_flagged(cfg: SimConfig) -> None:
    """No weight shift to read (a planar walker): nothing is flagged. A thigh skin turning inwards with the knee,
    and a gyro bias of ~18 deg/s on the thigh that no rest removed, move the early-stance rate by several deg/s in
    the other leg's sense through the stride's mean rate: on the first figure alone both were flagged as swapped.
    The rate relative to the stride's mean stays near 0."""
    res = process_session(simulate_session(cfg).streams)
    shift = {leg: lr.diagnostics.weight_shift_dps for leg, lr in res.legs.items()}
    assert all(abs(s[1]) < 2.0 for s in shift.values())
    assert side_verdict(shift["left"], shift["right"]) == "undecided"
    assert not any("side_in_doubt" in s.quality_reasons for lr in res.legs.values() for s in lr.strides)


def test_side_verdict_needs_both_legs_and_both_figures_in_the_other_sense() -> None:
    assert side_verdict((-5.0, -3.0), (6.0, 2.5)) == "swapped"
    assert side_verdict((-5.0, -3.0), (-6.0, -2.5)) == "undecided"  # one leg's sense only: no verdict
    assert side_verdict((-1.0, -3.0), (6.0, 2.5)) == "undecided"  # below the floor
    assert side_verdict((-5.0, 0.5), (6.0, 2.5)) == "undecided"  # the stride-mean-free figure does not agree
    assert side_verdict(None, (6.0, 2.5)) == "undecided"


def test_sensors_that_never_move_give_no_verdict_and_no_crash() -> None:
    """All-zero gyro and accelerometer (a sensor left on a table, or a driver fault): no label verdict, no strides,
    no exception (a division by the thigh's zero swing rate used to raise)."""
    from pipeline.types import RawSensorStream

    t = np.arange(3000) / 100.0
    streams = [RawSensorStream(sensor_id=f"L-{seg}", leg="left", segment=seg, fs_hz=100.0, t_s=t,
                               gyr=np.zeros((3000, 3)), acc=np.zeros((3000, 3))) for seg in ("thigh", "shank")]
    assert check_segments(streams[0], streams[1]).verdict == "undecided"
    res = process_session(streams)
    assert all(not lr.strides for lr in res.legs.values())


def test_the_weight_shift_does_not_lean_with_where_the_thigh_rests() -> None:
    """The walking direction comes from gravity during the strides: a thigh resting horizontal outside them (sitting)
    moves neither figure. The session's mean specific force leaned with it and read "sit, walk, sit" sessions of an
    independent simulator as swapped sides."""
    from scipy.spatial.transform import Rotation

    from pipeline.assignment import weight_shift_dps
    from pipeline.session import _leg_input, _synced

    sim = simulate_session(SimConfig(seed=3, n_strides=24, bout_strides=12, hip_3d=1.0, activities=("standing",)))
    st = {s.segment: s for s in sim.streams if s.leg == "left"}
    data, _ = _leg_input(_synced("left", st["thigh"], st["shank"], "walking", None), "walking", None)
    prep, strides = data.prep, data.events.strides
    args = (prep.valid, data.axes.j1, strides)
    before = weight_shift_dps(prep.gyr_thigh_rps, prep.acc_thigh_mps2, *args)
    outside = np.ones(prep.n, dtype=bool)
    for a, _, b in strides:
        outside[a:b + 1] = False
    seated = prep.acc_thigh_mps2.copy()  # the thigh turned 90 deg forward about the knee axis wherever it rests
    seated[outside] = Rotation.from_rotvec(np.pi / 2 * data.axes.j1).apply(seated[outside])
    padded = np.concatenate([seated, np.tile(seated[outside][:1], (10 * prep.n, 1))])  # and a long sit after
    pad = lambda x, v: np.concatenate([x, np.full((10 * prep.n, *x.shape[1:]), v, dtype=x.dtype)])  # noqa: E731
    after = weight_shift_dps(pad(prep.gyr_thigh_rps, 0.0), padded, pad(prep.valid, True), data.axes.j1, strides)
    assert before is not None and after == pytest.approx(before, abs=1e-9)


def test_the_knee_lies_below_the_thigh_sensor_and_above_the_shank_sensor() -> None:
    """Seel Eq. 5's sensor positions along each segment's mean specific force: the thigh sensor above the knee
    centre, the shank sensor below it, on a right order; the verdict needs the margin either way."""
    up = np.tile([0.0, 0.0, 9.81], (50, 1))
    valid = np.ones(50, dtype=bool)
    heights = centre_heights_m(np.array([0.02, 0.07, 0.18]), np.array([0.01, 0.05, -0.15]), up, up, valid)
    np.testing.assert_allclose(heights, (0.18, -0.15))
    assert segments_by_centre(heights) == "as_labelled"
    assert segments_by_centre((heights[1], heights[0])) == "swapped"
    assert segments_by_centre((0.01, -0.01)) == "undecided"
    assert segments_by_centre(None) == "undecided"
    tilted = np.tile([0.0, 9.81, 0.0], (50, 1))  # the mean specific force along the sensor's y axis
    assert centre_heights_m(np.array([0.0, 0.1, 0.0]), np.zeros(3), tilted, up, valid)[0] == pytest.approx(0.1)


def test_high_knees_between_walks_keep_the_labels_and_the_walk() -> None:
    """High knees lift the thigh faster than walking swings the shank, so over the session the swing rates read
    every leg's labels as exchanged, and the exchanged order took the lifts for strides and lost the walk. The joint
    centres put each thigh sensor above its knee: the labels stand, the walk's strides are found, and no stride lies
    inside the exercise."""
    sim = simulate_session(SimConfig(seed=2, n_strides=12, bout_strides=6, activities=("high_knees",), move_reps=20))
    by_leg = {leg: {s.segment: s for s in sim.streams if s.leg == leg} for leg in ("left", "right")}
    assert all(check_segments(d["thigh"], d["shank"]).verdict == "swapped" for d in by_leg.values())
    res = process_session(sim.streams)
    assert sum("joint centres put the sensor labelled thigh" in w for w in res.warnings) >= 1, res.warnings
    (_, t0, t1), = sim.info["non_gait_s"]
    for leg, lr in res.legs.items():
        assert lr.diagnostics.assignment == "as_labelled", leg
        steady = [t for t in sim.truth[leg].strides if t.steady]
        assert len(match_strides(lr.strides, steady)) == len(steady), leg
        assert not [s for s in lr.strides if t0 < s.t_end_s and s.t_start_s < t1], leg
        assert _rmse(sim, lr) < 5.0, leg


def test_high_knees_alone_give_no_stride_whatever_the_centres_say() -> None:
    """High knees alone: the swing rates read every leg's labels as exchanged and the exchanged order took the lifts
    for strides. Where the joint centres fit no body-worn lever arms in that order they confirm nothing, so the labels
    stand; as labelled the lifts are no gait: no stride, and no trace without gait."""
    sim = simulate_session(SimConfig(seed=101, walking=False, activities=("high_knees",), move_reps=30))
    res = process_session(sim.streams)
    assert sum("labels kept as given" in w and "joint centres" in w for w in res.warnings) == 2, res.warnings
    for lr in res.legs.values():
        assert lr.diagnostics.assignment == "as_labelled" and not lr.strides
        assert lr.diagnostics.trace_withheld == "no_gait"


def test_a_vetoed_leg_that_cannot_be_synchronised_again_is_skipped_with_its_reason(monkeypatch) -> None:
    """A leg whose exchange the joint centres veto is synchronised again as labelled; where that fails, the leg is
    skipped and says why, and none of the exchanged order's strides (the lifts of the high knees) is reported."""
    import pipeline.session as session

    sim = simulate_session(SimConfig(seed=2, n_strides=12, bout_strides=6, activities=("high_knees",), move_reps=20))
    synced = session._synced
    vetoed: list[str] = []

    def failing_after_a_veto(leg, *args, **kwargs):
        if inspect.stack()[1].function == "_processed_legs":  # a veto's re-synchronisation
            vetoed.append(leg)
            raise ValueError("less than one second of usable samples")
        return synced(leg, *args, **kwargs)

    monkeypatch.setattr(session, "_synced", failing_after_a_veto)
    res = process_session(sim.streams)
    assert vetoed, "the high knees' exchange was not vetoed"
    for leg in vetoed:
        assert leg not in res.legs
        assert f"{leg} leg skipped: less than one second of usable samples" in res.warnings, res.warnings
        assert any(w.startswith(f"{leg} leg: thigh and shank labels kept as given") for w in res.warnings)


def test_after_a_veto_the_exchanged_legs_are_judged_again(monkeypatch) -> None:
    """A veto changes the other leg's swings, so every exchange still standing is judged again on the legs processed
    after it, until a pass vetoes nothing: the high knees between walks veto on the first pass and the joint centres
    are asked once more."""
    import pipeline.session as session

    sim = simulate_session(SimConfig(seed=2, n_strides=12, bout_strides=6, activities=("high_knees",), move_reps=20))
    judge = session._centre_vetoes
    passes: list[list[str]] = []

    def recorded(*args, **kwargs):
        passes.append(judge(*args, **kwargs))
        return passes[-1]

    monkeypatch.setattr(session, "_centre_vetoes", recorded)
    res = process_session(sim.streams)
    assert passes[0] and passes[-1] == [] and len(passes) >= 2, passes
    assert all(lr.diagnostics.assignment == "as_labelled" for lr in res.legs.values())
