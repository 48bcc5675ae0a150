"""Gravity over whole gait cycles (pipeline.cycle_gravity): the segment's up direction at each foot strike, the
walking stride's knee over its mid-stance, and the running level it gives."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.constants import G_MPS2
from pipeline.cycle_gravity import cycle_up, knee_from_gravity_deg, up_at_samples, window_knee_deg
from pipeline.params import WALKING
from pipeline.phases import midstance_bounds
from pipeline.posture import standing_mask
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.walking import build_walking_leg_input

FS = 200.0
UP = np.array([0.0, 0.0, 1.0])


def _ry(theta: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) about the world's y (the hinge) by ``theta`` [rad]."""
    c, s = np.cos(theta), np.sin(theta)
    z, o = np.zeros_like(theta), np.ones_like(theta)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _swinging_sensor(mount: np.ndarray, lever_m: np.ndarray, impact_g: float, n_cycles: int = 6,
                     cycle_s: float = 0.7) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A sensor on a segment that swings +-50 deg (with a second harmonic) about the world's y while its pivot runs
    forward at 3 m/s, bobs 8 cm at twice the cycle rate, and takes a shock at every cycle start that moves the sensor
    from rest back to rest. Returns gyro (N, 3) [rad/s], specific force (N, 3) [m/s^2], rotations (N, 3, 3) and the
    cycle starts."""
    t = np.arange(int(n_cycles * cycle_s * FS) + 1) / FS
    w = 2 * np.pi / cycle_s
    theta = np.radians(50) * np.sin(w * t) + np.radians(10) * np.sin(2 * w * t + 0.7)
    dtheta = np.radians(50) * w * np.cos(w * t) + np.radians(10) * 2 * w * np.cos(2 * w * t + 0.7)
    ddtheta = -np.radians(50) * w**2 * np.sin(w * t) - np.radians(10) * 4 * w**2 * np.sin(2 * w * t + 0.7)
    rot = _ry(theta) @ mount
    omega_w = np.column_stack([np.zeros_like(t), dtheta, np.zeros_like(t)])
    alpha_w = np.column_stack([np.zeros_like(t), ddtheta, np.zeros_like(t)])
    r_w = _ry(theta) @ lever_m
    pivot_acc = np.column_stack([np.zeros_like(t), np.zeros_like(t), -0.04 * (2 * w) ** 2 * np.sin(2 * w * t)])
    acc_w = pivot_acc + np.cross(alpha_w, r_w) + np.cross(omega_w, np.cross(omega_w, r_w))
    starts = np.arange(n_cycles) * int(round(cycle_s * FS))
    # a shock along the segment as it points at the strike, fixed in the world: x'' of a Gaussian displacement
    # (sigma 8 ms), so the sensor comes back to rest and its samples see a band-limited signal
    sigma = 0.008
    for s0 in starts:
        u = t[s0:s0 + int(0.1 * FS)] - t[s0] - 4 * sigma
        shape = (u * u / sigma**4 - 1 / sigma**2) * np.exp(-u * u / (2 * sigma * sigma))
        acc_w[s0:s0 + u.size] += (impact_g * G_MPS2 * sigma**2) * shape[:, None] * (rot[s0] @ [0, 0, 1.0])
    gyr = np.einsum("nji,nj->ni", rot, omega_w)
    force = np.einsum("nji,nj->ni", rot, acc_w + G_MPS2 * UP)
    return gyr, force, rot, starts


@pytest.mark.parametrize("impact_g", [0.0, 10.0])
def test_cycle_mean_force_is_gravity_in_the_frame_at_the_strike(impact_g: float) -> None:
    rng = np.random.default_rng(3)
    mount = Rotation.random(random_state=rng).as_matrix()
    gyr, force, rot, starts = _swinging_sensor(mount, np.array([0.05, 0.04, -0.2]), impact_g)
    n = int(round(0.7 * FS))
    up = cycle_up(gyr, force, FS, starts[:-1], starts[:-1] + n)
    truth = np.einsum("nji,j->ni", rot[starts[:-1]], G_MPS2 * UP)
    cos = np.sum(up * truth, axis=1) / (np.linalg.norm(up, axis=1) * G_MPS2)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.3
    # the instantaneous reading at the strike is far from gravity: the cycle mean is what removes the motion
    inst = force[starts[:-1]]
    inst_cos = np.sum(inst * truth, axis=1) / (np.linalg.norm(inst, axis=1) * G_MPS2)
    assert np.degrees(np.arccos(np.clip(inst_cos, -1, 1))).max() > 5.0


def test_cycle_mean_of_half_a_cycle_is_not_gravity() -> None:
    """The cancellation needs whole cycles: over half of one the swing's acceleration stays in the mean."""
    gyr, force, rot, starts = _swinging_sensor(np.eye(3), np.array([0.0, 0.05, -0.25]), 0.0)
    half = int(round(0.35 * FS))
    up = cycle_up(gyr, force, FS, starts[:-1], starts[:-1] + half)
    truth = np.einsum("nji,j->ni", rot[starts[:-1]], G_MPS2 * UP)
    assert np.abs(np.linalg.norm(up - truth, axis=1)).min() > 0.5


def test_knee_from_gravity_follows_the_segments_about_the_hinge() -> None:
    rng = np.random.default_rng(5)
    m1, m2 = (Rotation.random(random_state=rng).as_matrix() for _ in range(2))
    j1, j2 = m1.T @ [0, 1.0, 0], m2.T @ [0, 1.0, 0]  # the world's y (the hinge) in each sensor frame
    stand1, stand2 = m1.T @ UP, m2.T @ UP
    # the thigh turned +30 deg about the hinge, the shank -25: flexion grows by 55 deg (rate g1.j1 - g2.j2)
    up1 = (_ry(np.radians([30.0]))[0] @ m1).T @ UP
    up2 = (_ry(np.radians([-25.0]))[0] @ m2).T @ UP
    knee = knee_from_gravity_deg(up1[None], up2[None], stand1, stand2, j1, j2, 4.0)
    assert knee[0] == pytest.approx(59.0, abs=1e-6)
    # a turn of the whole leg about the vertical changes nothing
    yaw = Rotation.from_euler("z", 70, degrees=True).as_matrix()
    up1y, up2y = (yaw @ _ry(np.radians([30.0]))[0] @ m1).T @ UP, (yaw @ _ry(np.radians([-25.0]))[0] @ m2).T @ UP
    assert knee_from_gravity_deg(up1y[None], up2y[None], stand1, stand2, j1, j2, 4.0)[0] == pytest.approx(59.0)


def test_a_long_run_keeps_its_level() -> None:
    """150 s of running at 200 Hz, quiet standing only before and after: too long for the bridge from standing
    (``FusionParams.bridge_max_span_s``). On this seed the filter's level alone put the left leg's peaks 5.9 deg
    high (its minima 8.3); the cycle-mean gravity holds both legs within 3 deg (-1.8 and -1.0)."""
    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, seed=0, impact_g=6.0, duration_s=150.0,
                                     bout_strides=200, activities=("standing",)))
    res = process_session(sim.streams, activity="running")
    for leg, lr in res.legs.items():
        assert lr.diagnostics is not None and lr.diagnostics.gravity_shift_deg is not None
        truth = sim.truth[leg]
        errs = []
        for s in lr.strides:
            k = int(np.argmin([abs(ts.t_start_s - s.t_start_s) for ts in truth.strides]))
            ts = truth.strides[k]
            if abs(ts.t_start_s - s.t_start_s) < 0.1 and ts.steady and s.quality >= 0.5:
                errs.append(s.peak_swing_flexion_deg - ts.peak_swing_flexion_deg)
        assert len(errs) > 150
        assert abs(float(np.mean(errs))) < 3.0


def test_the_gravity_knee_over_mid_stance_is_the_true_knee_whatever_the_mounting() -> None:
    """A walk with random mounting, lever arms, impacts and thigh wobble: over each stride's mid-stance the knee from
    the stride's mean gravity, carried to each sample by the gyros, follows the true knee to within a degree or
    two, with no joint centre fitted."""
    sim = simulate_session(SimConfig(seed=6, duration_s=60.0, legs=("left",), packet_loss=0.0, outages_per_min=0.0))
    truth = sim.truth["left"]
    by = {s.segment: s for s in sim.streams}
    params = dataclasses.replace(WALKING, posture=dataclasses.replace(
        WALKING.posture, standing_knee_deg=truth.stand_knee_deg))
    synced = synchronised_leg("left", by["thigh"], by["shank"], params)
    leg = build_walking_leg_input(synced.prep, params, axes=synced.axes, fit_gyr=synced.fit_gyr)
    strides = np.asarray(leg.events.strides)
    lo, hi = midstance_bounds(leg.events.strides, params.fusion.midstance_window)
    knee = window_knee_deg(leg, standing_mask(leg), params.fusion.gravity_tol_mps2, strides[:, [0, 2]], lo, hi)
    have = np.isfinite(knee)
    assert have.sum() > 0.5 * (hi - lo).sum()  # every measured stride gives it, starts and stops too
    err = knee[have] - truth.angle_at(leg.prep.t_s[have])
    p95 = np.percentile(np.abs(err), 95)
    assert abs(np.median(err)) < 0.5 and p95 < 1.5, (np.median(err), p95)


def test_cycle_gravity_is_the_same_in_any_grouping_of_the_cycles() -> None:
    """Thousands of cycles are integrated in several groups (pipeline.strapdown.cycle_blocks); each cycle's mean
    force and its carried gravity come out as when the cycle is integrated alone."""
    rng = np.random.default_rng(4)
    lengths = rng.integers(150, 260, size=2500)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    ends = starts + lengths
    gyr = rng.standard_normal((int(ends[-1]), 3))
    acc = rng.standard_normal((int(ends[-1]), 3)) + [0.0, 0.0, G_MPS2]
    lo, hi = starts + 20, starts + 60
    up, idx, owner, norm = up_at_samples(gyr, acc, FS, starts, ends, lo, hi)
    np.testing.assert_allclose(norm, np.linalg.norm(cycle_up(gyr, acc, FS, starts, ends), axis=1))
    for k in (0, 1234, 2499):
        up_k, idx_k, _, _ = up_at_samples(gyr, acc, FS, starts[k:k + 1], ends[k:k + 1], lo[k:k + 1], hi[k:k + 1])
        np.testing.assert_allclose(up[owner == k], up_k, atol=1e-9)
        assert idx[owner == k].tolist() == idx_k.tolist()
