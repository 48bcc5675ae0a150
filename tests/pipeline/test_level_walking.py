"""pipeline.level_walking and the session's level-gait check: a stair flight is not level walking."""

from __future__ import annotations

import numpy as np

from bench.matching import match_strides
from pipeline.level_walking import near_extension_share, next_to, not_level_walking, stance_above_swing
from pipeline.metrics import stride_values_many
from pipeline.params import PhaseParams
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def _stride(points: list[tuple[float, float]], n: int = 200) -> np.ndarray:
    x = np.array([p for p, _ in points]) / 100.0
    return np.interp(np.arange(n) / n, x, [v for _, v in points])


def test_stair_gait_is_far_from_extension_and_walking_is_not() -> None:
    """Perry's level-walking knee (contact ~5 deg, loading flexion ~18 deg, swing ~60 deg) spends most of its
    stride near extension; stair ascent (contact at ~60 deg, extension under load) and descent (flexion under load
    to ~75 deg before toe-off) do not."""
    walk = _stride([(0, 5), (12, 18), (40, 5), (60, 38), (72, 60), (100, 5)])
    up = _stride([(0, 62), (25, 35), (40, 15), (55, 10), (82, 92), (100, 62)])
    down = _stride([(0, 8), (25, 25), (55, 75), (75, 97), (95, 15), (100, 8)])
    t_s = np.arange(600) * 0.01
    angle = np.concatenate([walk, up, down])
    spans = np.array([(0.0, 2.0), (2.0, 4.0), (4.0, 6.0)])
    share = near_extension_share(angle, t_s, spans, PhaseParams().level_band_deg)
    assert share[0] > 0.6 and share[1] < 0.45 and share[2] < 0.4, share
    p = PhaseParams()
    assert not_level_walking(angle, t_s, spans, p.level_band_deg, p.level_min_share) == [1, 2]
    masked = angle.copy()
    masked[200:400] = np.nan  # a stride without an angle is not judged
    assert not_level_walking(masked, t_s, spans, p.level_band_deg, p.level_min_share) == [2]


def test_a_step_down_flexes_the_knee_more_in_stance_than_in_swing() -> None:
    """Level walking flexes the knee most in swing (~60 deg) and ~18 deg in loading response; stepping down off a
    step lowers the body on a stance knee flexed to ~66 deg and swings a leg flexed ~29 deg. A long pause near
    extension on the step (both feet on it) keeps the step-down's share near extension high: only where the knee
    flexes most tells it."""
    walk = _stride([(0, 5), (12, 18), (40, 5), (60, 38), (72, 60), (100, 5)])
    down = _stride([(0, 5), (10, 5), (35, 66), (55, 10), (65, 12), (80, 29), (100, 5)])
    t_s = np.arange(400) * 0.01
    angle = np.concatenate([walk, down])
    strides = [(0, 120, 200), (200, 330, 399)]
    values = stride_values_many(angle, t_s, strides)
    p = PhaseParams()
    assert values[1].peak_swing_flexion_deg < 30.0 < values[1].rom_deg - 30.0
    assert stance_above_swing(values, p.stance_above_swing_deg) == [1]
    assert not_level_walking(angle, t_s, np.array([(0.0, 2.0), (2.0, 3.99)]), p.level_band_deg,
                             p.level_min_share) == []


def test_a_walking_stride_flexed_most_in_stance_goes_with_its_neighbours_and_is_said() -> None:
    """The session's level-gait check on a processed walk whose one stride flexes 25 deg more in stance than at its
    swing peak (its range widened): that stride and the two that share its heel strikes (the step onto and off the
    step) are dropped, the session says why, and the other strides stay."""
    import dataclasses

    from pipeline.session import _level_strides

    sim = simulate_session(SimConfig(pattern="normal", seed=2, duration_s=60.0, bout_strides=10,
                                     activities=("standing",)))
    lr = process_session(sim.streams).legs["left"]
    k = len(lr.strides) // 2
    s = lr.strides[k]
    assert abs(lr.strides[k - 1].t_end_s - s.t_start_s) < 1e-9 and abs(s.t_end_s - lr.strides[k + 1].t_start_s) < 1e-9
    down = dataclasses.replace(lr, strides=[*lr.strides[:k], dataclasses.replace(s, rom_deg=s.rom_deg + 25.0),
                                            *lr.strides[k + 1:]])
    warnings: list[str] = []
    kept = _level_strides({"left": down}, PhaseParams(), warnings)["left"]
    assert [x.t_start_s for x in kept.strides] == [x.t_start_s for i, x in enumerate(lr.strides)
                                                   if i not in (k - 1, k, k + 1)]
    assert "left leg: 1 stride(s) dropped: the knee flexed more in stance than in swing (stepping down, not level " \
           "gait)" in warnings
    assert "left leg: 2 stride(s) dropped: the stride led onto or off a stair or a step" in warnings
    assert _level_strides({"left": lr}, PhaseParams(), [])["left"].strides == lr.strides


def test_a_stair_flight_gives_no_strides_and_keeps_the_walk() -> None:
    """Ten steps up and ten down, step over step between two walking bouts: the legs alternate like gait and the
    strides used to enter trends with ~100 deg of swing flexion; now none lies inside the flight, and the walking
    strides are all kept."""
    sim = simulate_session(SimConfig(pattern="normal", seed=1, duration_s=60.0, bout_strides=10,
                                     activities=("stair_flight",)))
    stairs = [(a, b) for kind, a, b in sim.info["non_gait_s"] if kind.startswith("stairs")]
    assert stairs
    res = process_session(sim.streams)
    inside = [s for lr in res.legs.values() for s in lr.strides
              if any(a < s.t_end_s and s.t_start_s < b for a, b in stairs)]
    assert not inside, [(s.leg, s.t_start_s, s.peak_swing_flexion_deg) for s in inside]
    assert any("stairs or step-ups" in w for w in res.warnings)
    for leg, lr in res.legs.items():
        steady = [t for t in sim.truth[leg].strides if t.steady]
        assert len(match_strides(lr.strides, steady)) >= 0.95 * len(steady), leg


def test_the_strides_next_to_a_stair_step_are_found() -> None:
    """Strides share heel strikes within a bout: the one before a stair stride and the one after it; a stride of
    another bout (a pause between) is not next to it."""
    spans = np.array([(0.0, 1.1), (1.1, 2.2), (2.2, 3.3), (3.3, 4.4), (6.0, 7.1)])
    assert next_to(spans, [2]) == [1, 3]
    assert next_to(spans, [3]) == [2]
    assert next_to(spans, [1, 2]) == [0, 3]
    assert next_to(spans, []) == []


def test_a_step_onto_a_landing_is_no_gait_stride() -> None:
    """An exercise session without walking (3-D knee and hip): the last step of a stair flight, onto the landing,
    kept its knee near extension long enough to pass as level gait and entered trends (quality 0.75, peak 47 deg);
    it led off a stair stride, so it is a transition and is dropped with the flight. Which test drops it depends on
    the left shank's clock correction (-9.7 ms: the transition rule; -11.2 ms: the other leg's anti-phase test, as
    with the simulator's shocks balanced, ``impact_balanced``); either way it is dropped as no gait.
    """
    sim = simulate_session(SimConfig(seed=3, duration_s=90.0, bout_strides=12, walking=False, hip_3d=1.0, knee_3d=1.0,
                                     move_reps=6, activities=("sitting", "seated_extension", "sit_to_stand", "jump",
                                                              "step_test", "stair_flight"), impact_balanced=False))
    res = process_session(sim.streams)
    assert not [s for lr in res.legs.values() for s in lr.strides if s.quality >= 0.5]
    assert any("led onto or off a stair or a step" in w or "did not swing in anti-phase" in w
               for w in res.warnings if w.startswith("left leg"))
