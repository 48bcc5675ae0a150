"""pipeline.quiet_bridge: the level carried from rest by the gyros, and its check of the mid-stance level."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import pipeline.walking as walking
from bench.matching import match_strides
from pipeline.params import RUNNING, WALKING
from pipeline.session import process_session
from pipeline.simulate import SimConfig, SimSession, simulate_session
from pipeline.types import LegResult


def _sim(seed: int) -> SimSession:
    """A session whose walks are wholly measured (no packet lost): a walk with a hole has no bridge."""
    return simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=seed, duration_s=90.0, bout_strides=12,
                                      packet_loss=0.0, outages_per_min=0.0))


def _mean_peak_error(lr: LegResult, sim: SimSession, leg: str) -> float:
    truth = sim.truth[leg].strides
    pairs = match_strides(lr.strides, truth)
    assert len(pairs) > 20
    return float(np.mean([lr.strides[i].peak_swing_flexion_deg - truth[j].peak_swing_flexion_deg for i, j in pairs]))


def test_legs_whose_levels_agree_keep_the_mid_stance_level() -> None:
    sim = _sim(0)
    for lr in process_session(sim.streams, activity="walking").legs.values():
        assert lr.diagnostics.bridge_check_deg is not None
        assert abs(lr.diagnostics.bridge_check_deg) < 1.5
        assert not lr.diagnostics.level_bridged


@pytest.mark.parametrize("seed", [1, 4, 5, 6])
def test_a_failed_joint_centre_fit_is_caught_and_the_leg_takes_the_bridged_level(
        seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Sensor positions 20-30 cm off (as a clock error absorbed by the joint-centre fit leaves them) move the
    mid-stance level by degrees; the static angles in standing do not see them, so the check takes the bridged level
    and the leg's peak error returns to within 1.5 deg of the uncorrupted run's. (Of seeds 0-6, on 0 and 2 the
    corrupted fit moves the level by less than the check's bound, and on 3 the check reads 2.8 deg, just inside it.)
    The strides levelled by the cycle-mean gravity (the default) need no joint centre at all: there the failed fit
    moves nothing."""
    sim = _sim(seed)
    mid_stance = dataclasses.replace(WALKING, fusion=dataclasses.replace(WALKING.fusion, gravity_level=False))
    clean = _mean_peak_error(process_session(sim.streams, activity="walking", params=mid_stance).legs["left"], sim,
                             "left")
    clean_gravity = _mean_peak_error(process_session(sim.streams, activity="walking").legs["left"], sim, "left")
    fit = walking.fit_joint_centres

    def off_by_decimetres(*args: object, **kwargs: object) -> object:
        c = fit(*args, **kwargs)
        return dataclasses.replace(c, o1=c.o1 + np.array([0.25, -0.15, 0.1]), o2=c.o2 + np.array([-0.1, 0.2, 0.05]))

    monkeypatch.setattr(walking, "fit_joint_centres", off_by_decimetres)
    unchecked = dataclasses.replace(mid_stance, fusion=dataclasses.replace(mid_stance.fusion, bridge_disagree_deg=1e9))
    broken = process_session(sim.streams, activity="walking", params=unchecked).legs["left"]
    assert abs(_mean_peak_error(broken, sim, "left") - clean) > WALKING.fusion.bridge_disagree_deg
    result = process_session(sim.streams, activity="walking", params=mid_stance)
    checked = result.legs["left"]
    assert checked.diagnostics.level_bridged
    assert any(w.startswith("left leg: the knee angle's level in motion disagreed") for w in result.warnings)
    assert abs(_mean_peak_error(checked, sim, "left") - clean) < 1.5
    gravity = process_session(sim.streams, activity="walking").legs["left"]
    assert not gravity.diagnostics.level_bridged
    assert abs(_mean_peak_error(gravity, sim, "left") - clean_gravity) < 0.3


@pytest.mark.parametrize("gravity", [False, True])
def test_a_running_leg_moved_by_a_failed_joint_centre_fit_is_levelled_again(
        monkeypatch: pytest.MonkeyPatch, gravity: bool) -> None:
    """The same failure in running (the EKF's level rests on the accelerometer angle in motion): a leg moved by
    ~10 deg returns to within 2 deg of the clean run's error. By default the cycle-mean gravity's level takes it back
    (pipeline.cycle_gravity) before the bridges see anything; without that level (where no whole cycles are left)
    whole rest-to-rest bridges catch it (on the data they were written on: the simulator's shocks not balanced)."""
    import pipeline.running as running

    params = RUNNING if gravity else dataclasses.replace(
        RUNNING, fusion=dataclasses.replace(RUNNING.fusion, gravity_level=False))
    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, seed=1, duration_s=90.0, bout_strides=12,
                                     impact_balanced=gravity))
    clean_leg = process_session(sim.streams, activity="running", params=params).legs["left"]
    assert not clean_leg.diagnostics.level_bridged
    clean = _mean_peak_error(clean_leg, sim, "left")
    fit = running.fit_joint_centres

    def off_by_decimetres(*args: object, **kwargs: object) -> object:
        c = fit(*args, **kwargs)
        return dataclasses.replace(c, o1=c.o1 + np.array([0.25, -0.15, 0.1]), o2=c.o2 + np.array([-0.1, 0.2, 0.05]))

    monkeypatch.setattr(running, "fit_joint_centres", off_by_decimetres)
    leg = process_session(sim.streams, activity="running", params=params).legs["left"]
    if gravity:
        moved = leg.diagnostics.gravity_shift_deg - clean_leg.diagnostics.gravity_shift_deg
        assert abs(moved) > 6.5 and not leg.diagnostics.level_bridged
    else:
        assert leg.diagnostics.gravity_shift_deg is None
        assert leg.diagnostics.bridge_check_deg is not None and abs(leg.diagnostics.bridge_check_deg) > 6.5
        assert leg.diagnostics.level_bridged
    assert abs(_mean_peak_error(leg, sim, "left") - clean) < 2.0


def _recorded_bridges(monkeypatch: pytest.MonkeyPatch, cfg: SimConfig
                      ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per leg processed, (bridged angle, thigh heading, standing, measured and usable masks) of the walking
    policy."""
    import pipeline.policy as policy
    import pipeline.quiet_bridge as quiet_bridge

    seen: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def recording(leg, zero_deg, params, standing):  # noqa: ANN001, ANN202 - the wrapped signature
        out = quiet_bridge.bridged_angle(leg, zero_deg, params, standing)
        seen.append((out, quiet_bridge.heading_deg(leg), standing, leg.prep.measured(), leg.prep.valid))
        return out

    monkeypatch.setattr(policy, "bridged_angle", recording)
    process_session(simulate_session(cfg).streams, activity="walking")
    return seen


def _pieces(bridged: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate(([0], np.isfinite(bridged).astype(int), [0]))))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def test_bridges_run_from_standing_to_standing_and_never_across_a_turn(monkeypatch: pytest.MonkeyPatch) -> None:
    """U-turns in every other bout: the thigh's heading shows them (> 120 deg); bridges run from quiet standing to
    quiet standing, and none holds a turn."""
    seen = _recorded_bridges(monkeypatch, SimConfig(pattern="normal", fs_hz=100.0, seed=2, duration_s=90.0,
                                                    bout_strides=12, walking_turns=True, packet_loss=0.0,
                                                    outages_per_min=0.0))
    limit = WALKING.fusion.bridge_max_turn_deg
    for bridged, heading, standing, _, _ in seen:
        assert np.ptp(heading) > 120.0
        pieces = _pieces(bridged)
        assert pieces
        for a, b in pieces:
            assert np.abs(heading[a:b] - heading[a]).max() <= limit
            assert standing[max(a - 1, 0)] and standing[min(b, standing.size - 1)]


def test_a_walk_with_a_hole_is_not_bridged_from_either_end(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bursty packet loss: a walk with a hole, filled or not, has no measured integral to its far end, and none is
    taken from one end alone (nothing would check its drift). Every bridge runs over measured samples from standing
    to standing."""
    seen = _recorded_bridges(monkeypatch, SimConfig(pattern="normal", fs_hz=100.0, seed=4, duration_s=90.0,
                                                    bout_strides=8, walking_turns=False, packet_loss=0.01,
                                                    loss_model="bursty", outages_per_min=0.0))
    bridges = 0
    for bridged, _, standing, measured, _ in seen:
        assert not measured.all()
        for a, b in _pieces(bridged):
            assert measured[a:b].all()
            assert standing[max(a - 1, 0)] and standing[min(b, standing.size - 1)]
            bridges += 1
    assert bridges  # the walks that lost nothing are bridged


def test_cf_fallback_strides_of_a_bridged_leg_move_with_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """A leg that takes the bridged level moves its CF fallback strides too (their CF follows the accelerometer's
    level in motion, which the check rejected): with GO's drift limit at 1 deg half the strides fall back, and both
    kinds come back to within 1 deg of the uncorrupted run's error."""
    sim = _sim(1)
    fallback = dataclasses.replace(WALKING, fusion=dataclasses.replace(WALKING.fusion, drift_max_deg=1.0))

    def by_estimator(lr: LegResult) -> dict[str, float]:
        truth = sim.truth["left"].strides
        errs: dict[str, list[float]] = {}
        for i, j in match_strides(lr.strides, truth):
            s = lr.strides[i]
            errs.setdefault(s.estimator, []).append(s.peak_swing_flexion_deg - truth[j].peak_swing_flexion_deg)
        return {k: float(np.mean(v)) for k, v in errs.items() if len(v) >= 5}

    clean = by_estimator(process_session(sim.streams, activity="walking", params=fallback).legs["left"])
    fit = walking.fit_joint_centres

    def off_by_decimetres(*args: object, **kwargs: object) -> object:
        c = fit(*args, **kwargs)
        return dataclasses.replace(c, o1=c.o1 + np.array([0.25, -0.15, 0.1]), o2=c.o2 + np.array([-0.1, 0.2, 0.05]))

    monkeypatch.setattr(walking, "fit_joint_centres", off_by_decimetres)
    leg = process_session(sim.streams, activity="walking", params=fallback).legs["left"]
    assert leg.diagnostics.level_bridged
    broken = by_estimator(leg)
    assert set(clean) == set(broken) == {"go", "cf"}
    for name in ("go", "cf"):
        assert abs(broken[name] - clean[name]) < 1.0


def test_fallback_strides_are_checked_on_their_own_bridged_strides() -> None:
    """A CF fallback stride's level is the CF's, not the mid-stance level of a GO that failed there: the bridges
    check it on the fallback strides themselves (``pipeline.quiet_bridge.stride_check``), where they reach at least
    ``FusionParams.bridge_min_strides`` of them whole."""
    from pipeline.quiet_bridge import stride_check

    p = WALKING.fusion
    n = 1000
    cf = 20 * np.sin(np.linspace(0, 30, n))
    bridged = cf + 5.0
    bridged[:100] = np.nan  # the first stride is not bridged throughout
    lo, hi = np.arange(0, 1000, 100), np.arange(100, 1100, 100)
    assert stride_check(bridged - cf, lo, hi, p.bridge_min_strides) == pytest.approx(5.0)
    k = p.bridge_min_strides
    assert stride_check(bridged - cf, lo[:k], hi[:k], p.bridge_min_strides) is None  # one of the k is not whole
    assert stride_check(bridged - cf, lo[1:k + 1], hi[1:k + 1], p.bridge_min_strides) == pytest.approx(5.0)


def test_a_leg_whose_go_failed_everywhere_keeps_its_cf_level(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every stride a CF fallback (GO found no zero crossing) and GO's mid-stance levels 8 deg off, as a failed GO
    leaves them: the level check must not read those levels (it skips strides whose GO failed), and the CF strides
    keep the level their own bridged strides confirm."""
    import pipeline.policy as policy

    sim = _sim(0)
    base = process_session(sim.streams, activity="walking")
    offsets = policy.stance_offsets

    def failed(go_diag: object, p: object, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(lo.size, dtype=bool), np.zeros(lo.size, dtype=bool)

    def off_by_8(*args: object) -> tuple[np.ndarray, np.ndarray]:
        offs, counts = offsets(*args)
        return offs + 8.0, counts

    monkeypatch.setattr(policy, "_go_failures", failed)
    monkeypatch.setattr(policy, "stance_offsets", off_by_8)
    res = process_session(sim.streams, activity="walking")
    for leg, lr in res.legs.items():
        assert lr.strides and all(s.estimator == "cf" for s in lr.strides)
        assert not lr.diagnostics.level_bridged
        assert lr.diagnostics.bridge_check_deg is not None and abs(lr.diagnostics.bridge_check_deg) < 3.0
        assert abs(_mean_peak_error(lr, sim, leg) - _mean_peak_error(base.legs[leg], sim, leg)) < 1.5


def test_cf_fallback_strides_off_level_are_moved_and_said_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every other stride a CF fallback whose level is 8 deg off, the GO strides right: the fallback strides are
    moved by their own check, and the leg says so (level_bridged, the fallback strides' own figure, the warning),
    although the GO strides' check agrees."""
    import pipeline.policy as policy

    sim = _sim(0)
    base = process_session(sim.streams, activity="walking")
    fuse = policy.fuse

    def every_other(go_diag: object, p: object, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.arange(lo.size) % 2 == 1, np.zeros(lo.size, dtype=bool)

    def cf_off_by_8(leg: object, go_rel: np.ndarray, go_diag: object, cf: np.ndarray) -> object:
        return fuse(leg, go_rel, go_diag, cf + 8.0)

    monkeypatch.setattr(policy, "_go_failures", every_other)
    monkeypatch.setattr(policy, "fuse", cf_off_by_8)
    res = process_session(sim.streams, activity="walking")
    for leg, lr in res.legs.items():
        d = lr.diagnostics
        assert sum(s.estimator == "cf" for s in lr.strides) >= 5
        assert d.bridge_check_deg is not None and abs(d.bridge_check_deg) < 3.0
        assert d.fallback_bridge_check_deg is not None and abs(d.fallback_bridge_check_deg + 8.0) < 2.0
        assert d.level_bridged
        assert any(w.startswith(f"{leg} leg:") and "CF fallback strides" in w for w in res.warnings)
        assert abs(_mean_peak_error(lr, sim, leg) - _mean_peak_error(base.legs[leg], sim, leg)) < 1.5
