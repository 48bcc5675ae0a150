"""A knee that is no hinge (pipeline.simulate's 3-D chain): the tibia turns about its long axis as the knee flexes
and ab/adducts, and the hip and pelvis move out of the sagittal plane. The axis fit, the clock cues and the angles
must hold up (pipeline.axes.fit_joint_axes with ``up`` and ``gd2_rps2``, pipeline.sync.clock_model)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.matching import match_strides
from pipeline.axes import (
    angular_acceleration,
    axis_angle_deg,
    axis_up,
    estimate_sync_lag_s,
    fit_joint_axes,
    level_directions,
)
from pipeline.params import WALKING
from pipeline.prepare import prepare_leg
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.walking import fit_gyros

_CLEAN = dict(gyro_noise_dps=0.0, gyro_bias_dps=0.0, gyro_bias_walk_dps=0.0, acc_noise_ms2=0.0, acc_bias_ms2=0.0,
              packet_loss=0.0, outages_per_min=0.0, wobble_level=0.0, impact_level=0.0, clock_drift_ppm=0.0)


def _streams(sim, leg: str):
    by = {(s.leg, s.segment): s for s in sim.streams}
    return by[(leg, "thigh")], by[(leg, "shank")]


def _true_axes(sim, leg: str) -> tuple[np.ndarray, np.ndarray]:
    """Each segment's medio-lateral (y) axis in its sensor frame: the flexion axis of the 3-D chain."""
    p = leg[0].upper()
    return tuple(np.array(sim.info["sensors"][f"{p}-{seg}"]["mounting"]).T @ np.array([0.0, 1.0, 0.0])
                 for seg in ("thigh", "shank"))


def _true_lag_ms(sim, leg: str) -> float:
    """How far the shank's stamps run behind the thigh's (the first sample always arrives: its stamp minus its true
    time is the sensor's offset)."""
    off = [st.t_s[0] - sim.info["sensors"][f"{leg[0].upper()}-{st.segment}"]["start_s"] for st in _streams(sim, leg)]
    return 1000.0 * (off[1] - off[0])


@pytest.fixture(scope="module")
def rotating_tibia():
    """Twice the typical tibial axial rotation and ab/adduction, planar hip: the hinge fit leans."""
    return simulate_session(SimConfig(pattern="normal", seed=1, duration_s=90.0, bout_strides=12, knee_3d=2.0,
                                      sync_offset_ms=0.0, **_CLEAN))


def test_the_hinge_fit_leans_and_the_flexion_axis_is_levelled(rotating_tibia) -> None:
    """Seel's hinge fits an oblique axis leaning towards the long axes; turned towards the plane perpendicular to the
    mean specific force (to within ``level_lean_deg``) it comes back to the segments' flexion axes."""
    for leg in ("left", "right"):
        prep = prepare_leg(leg, *_streams(rotating_tibia, leg))
        g1, g2 = fit_gyros(prep, WALKING.axes.fit_cutoff_hz)
        up = axis_up(prep, WALKING.axes)
        assert up is not None
        axes = fit_joint_axes(g1, g2, prep.valid, WALKING.axes, up=up)
        (h1, h2), (y1, y2) = axes.hinge(), _true_axes(rotating_tibia, leg)
        assert axis_angle_deg(h2, y2) > 10.0 and axis_angle_deg(h1, y1) > 10.0  # the free hinge leans
        assert axis_angle_deg(axes.j2, y2) < 0.5 * axis_angle_deg(h2, y2)
        # the thigh's hinge also leans forwards (towards the tibia's axis as the flexed knee carries it), which no
        # level tells: only its upward part goes
        assert axis_angle_deg(axes.j1, y1) < axis_angle_deg(h1, y1) - 5.0
        for j, u in ((axes.j1, up[0]), (axes.j2, up[1])):
            assert abs(np.degrees(np.arcsin(abs(j @ u)))) <= WALKING.axes.level_lean_deg + 1e-6
        assert axes.leaning


def test_a_lean_within_the_level_uncertainty_is_kept() -> None:
    """On the planar chain the hinge is the flexion axis: levelling moves nothing (lean below the bound)."""
    sim = simulate_session(SimConfig(pattern="normal", seed=2, duration_s=60.0, bout_strides=12, **_CLEAN))
    prep = prepare_leg("left", *_streams(sim, "left"))
    g1, g2 = fit_gyros(prep, WALKING.axes.fit_cutoff_hz)
    axes = fit_joint_axes(g1, g2, prep.valid, WALKING.axes, up=axis_up(prep, WALKING.axes))
    assert axes.hinge_j1 is None and axes.hinge_j2 is None
    assert not axes.leaning


def test_level_directions_need_a_reading_accelerometer() -> None:
    n = 100
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    up = level_directions(acc, acc, np.ones(n, dtype=bool))
    assert up is not None and np.allclose(up[0], [0.0, 0.0, 1.0])
    assert level_directions(np.zeros((n, 3)), acc, np.ones(n, dtype=bool)) is None


def test_axes_fitted_with_the_lag_are_not_bent_by_it() -> None:
    """3-D hip motion and a 20 ms shank lag: the axes alone absorb part of the lag and the hinge cue then reads a
    fraction of it; fitted together with the lag, the axes stay within a degree and the hinge cue reads the lag."""
    sim = simulate_session(SimConfig(pattern="normal", seed=1, duration_s=90.0, bout_strides=12, hip_3d=1.0,
                                     sync_offset_ms=10.0, **_CLEAN))
    lag_ms = _true_lag_ms(sim, "left")
    assert abs(lag_ms) > 15.0  # this seed's sensors are far apart
    prep = prepare_leg("left", *_streams(sim, "left"))
    g1, g2 = fit_gyros(prep, WALKING.axes.fit_cutoff_hz)
    y1, y2 = _true_axes(sim, "left")
    alone = fit_joint_axes(g1, g2, prep.valid, WALKING.axes)
    joint = fit_joint_axes(g1, g2, prep.valid, WALKING.axes, gd2_rps2=angular_acceleration(g2, prep.fs_hz))
    assert max(axis_angle_deg(alone.j1, y1), axis_angle_deg(alone.j2, y2)) > 2.0
    assert max(axis_angle_deg(joint.j1, y1), axis_angle_deg(joint.j2, y2)) < 1.0
    read = {name: 1000 * estimate_sync_lag_s(g1, g2, ax.j1, ax.j2, prep.valid, prep.fs_hz, max_lag_s=0.06)
            for name, ax in (("alone", alone), ("joint", joint))}
    assert abs(read["alone"] - lag_ms) > 8.0
    assert abs(read["joint"] - lag_ms) < 2.0


def test_the_hinge_clock_cue_is_not_trusted_on_a_rotating_tibia() -> None:
    """The tibia's axial rotation makes the hinge cue read a lag that is not there; the hinge fit leans, so the leg's
    clock follows the joint-centre cue (within 3 ms of the truth)."""
    sim = simulate_session(SimConfig(pattern="normal", seed=0, duration_s=90.0, bout_strides=12, knee_3d=1.0,
                                     sync_offset_ms=5.0))
    errors = {}
    for leg in ("left", "right"):
        thigh, shank = _streams(sim, leg)
        synced = synchronised_leg(leg, thigh, shank, WALKING)
        prep = prepare_leg(leg, thigh, shank)
        g1, g2 = fit_gyros(prep, WALKING.axes.fit_cutoff_hz)
        h1, h2 = synced.axes.hinge()
        hinge = estimate_sync_lag_s(g1, g2, h1, h2, prep.valid, prep.fs_hz, max_lag_s=0.06)
        truth = _true_lag_ms(sim, leg)
        errors[leg] = (1000 * hinge - truth, (synced.shank_lag_ms or 0.0) - truth)
    assert max(abs(e[0]) for e in errors.values()) > 4.0, errors  # the hinge alone is off
    assert all(abs(e[1]) < 3.0 for e in errors.values()), errors


def test_a_rotating_tibia_keeps_the_swing_peak() -> None:
    """End to end: typical 3-D knee and hip motion (x1) leave the swing peak within the sweep's targets."""
    sim = simulate_session(SimConfig(pattern="normal", seed=3, duration_s=90.0, bout_strides=12, knee_3d=1.0,
                                     hip_3d=1.0))
    res = process_session(sim.streams, activity="walking")
    err = []
    for leg, lr in res.legs.items():
        truth = sim.truth[leg].strides
        err += [lr.strides[i].peak_swing_flexion_deg - truth[j].peak_swing_flexion_deg
                for i, j in match_strides(lr.strides, truth) if truth[j].steady]
    err_arr = np.array(err)
    assert err_arr.size > 50
    assert abs(err_arr.mean()) < 1.5 and np.abs(err_arr).max() < 4.0


def test_the_levelling_can_be_switched_off() -> None:
    sim = simulate_session(SimConfig(pattern="normal", seed=1, duration_s=40.0, bout_strides=8, knee_3d=2.0,
                                     **_CLEAN))
    prep = prepare_leg("left", *_streams(sim, "left"))
    off = dataclasses.replace(WALKING.axes, axis_level=False)
    assert axis_up(prep, off) is None


def test_the_diagnostics_say_how_far_the_hinge_leaned(rotating_tibia) -> None:
    res = process_session(rotating_tibia.streams, activity="walking")
    for lr in res.legs.values():
        d = lr.diagnostics
        assert d is not None and d.knee_axes_levelled
        assert d.hinge_lean_deg is not None and max(d.hinge_lean_deg) > WALKING.axes.level_lean_deg
    planar = simulate_session(SimConfig(pattern="normal", seed=2, duration_s=40.0, bout_strides=8, **_CLEAN))
    for lr in process_session(planar.streams, activity="walking").legs.values():
        assert not lr.diagnostics.knee_axes_levelled
        assert max(lr.diagnostics.hinge_lean_deg) <= WALKING.axes.level_lean_deg
