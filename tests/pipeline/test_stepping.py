"""pipeline.stepping and the session's step check: marching in place is not gait."""

from __future__ import annotations

import numpy as np

from bench.matching import match_strides
from pipeline.params import PhaseParams
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.stepping import lowered_not_stepped, thigh_landing_deg, thigh_swing_deg

FS_HZ = 100.0


def _stride_rate(swing_deg: float, stance_deg: float, n_stance: int = 60, n_swing: int = 40) -> np.ndarray:
    """A thigh rate [deg/s] turning by ``stance_deg`` over the stance and ``swing_deg`` over the swing."""
    return np.concatenate([np.full(n_stance, stance_deg * FS_HZ / n_stance),
                           np.full(n_swing, swing_deg * FS_HZ / n_swing)])


def test_the_thigh_swing_is_summed_from_toe_off_to_heel_strike() -> None:
    """Walking's thigh turns back through the stance and forward through the swing; a march's the other way round.
    A masked sample adds nothing."""
    rate = np.concatenate([_stride_rate(+35.0, -35.0), _stride_rate(-38.0, +38.0), [0.0]])
    strides = [(0, 60, 100), (100, 160, 200)]
    swing = thigh_swing_deg(rate, strides, FS_HZ)
    # the heel strike's own sample belongs to the swing it ends: one sample of the next stance (or 0) added
    np.testing.assert_allclose(swing, [35.0 + 38.0 / 60, -38.0], atol=1e-9)
    holed = rate.copy()
    holed[170:180] = np.nan
    assert thigh_swing_deg(holed, strides, FS_HZ)[1] == -38.0 * 30 / 40
    p = PhaseParams()
    assert lowered_not_stepped(rate, strides, FS_HZ, p) == {1}
    assert lowered_not_stepped(rate, [], FS_HZ, p) == set()


def test_a_running_stride_whose_thigh_retracts_before_the_strike_is_a_step() -> None:
    """Running: the thigh extends through the stance to push-off (-25 deg over 35 samples), flexes forward through
    early swing (+50 over 25) and retracts before the strike (-8 over 40). The detected toe-off lies in mid-swing
    (sample 60), from where the thigh turns back, but it lands 42 deg forward of push-off: a step. A march's thigh
    lands where it stood."""
    run = np.concatenate([np.full(35, -25.0 * FS_HZ / 35), np.full(25, 50.0 * FS_HZ / 25),
                          np.full(40, -8.0 * FS_HZ / 40)])
    march = _stride_rate(-38.0, +38.0)
    rate = np.concatenate([run, march, [0.0]])
    strides = [(0, 60, 100), (100, 160, 200)]
    swing = thigh_swing_deg(rate, strides, FS_HZ)
    assert swing[0] < 0.0 and swing[1] < 0.0
    landing = thigh_landing_deg(rate, strides, FS_HZ)
    # from push-off (the least) to the strike, with the strike's own sample of the next stance
    np.testing.assert_allclose(landing, [50.0 - 8.0 + 38.0 / 60, 0.0], atol=1e-9)
    assert lowered_not_stepped(rate, strides, FS_HZ, PhaseParams()) == {1}


def test_marching_in_place_gives_no_strides_and_keeps_the_walk() -> None:
    """Twelve marching steps a leg between walking bouts: the legs alternate like gait, the knee stays near
    extension through the stance and the shank swings forward as each foot comes down, so each looks like a stride;
    none lies inside the march, the session says why, and the walking strides are kept."""
    sim = simulate_session(SimConfig(pattern="normal", seed=3, duration_s=60.0, bout_strides=10,
                                     activities=("march",), move_reps=12))
    marches = [(a, b) for kind, a, b in sim.info["non_gait_s"] if kind == "march"]
    assert marches
    res = process_session(sim.streams)
    inside = [s for lr in res.legs.values() for s in lr.strides
              if any(a < s.t_end_s and s.t_start_s < b for a, b in marches)]
    assert not inside, [(s.leg, s.t_start_s) for s in inside]
    assert any("did not turn forward" in w for w in res.warnings), res.warnings
    for leg, lr in res.legs.items():
        assert lr.diagnostics is not None and lr.diagnostics.lowered_strides >= 10, leg
        steady = [t for t in sim.truth[leg].strides if t.steady]
        assert len(match_strides(lr.strides, steady)) >= 0.95 * len(steady), leg


def test_crouch_gait_keeps_every_stride() -> None:
    """Crouch gait swings the thigh least of the simulator's walking patterns (+7 deg at its 1st percentile): every
    stride is still a step."""
    sim = simulate_session(SimConfig(pattern="crouch", seed=4, duration_s=60.0))
    res = process_session(sim.streams)
    for leg, lr in res.legs.items():
        assert lr.diagnostics is not None and lr.diagnostics.lowered_strides == 0, leg
        assert lr.strides, leg
