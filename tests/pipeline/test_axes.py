"""pipeline.axes: Seel Eq. 2 axis fit against a known hinge, sign convention, Eq. 5-7 on exact kinematics, Eq. 5 with
accelerometer biases on simulated sessions."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.axes import (
    JointAxes,
    JointCentres,
    accelerometer_angle_deg,
    angular_acceleration,
    axis_angle_deg,
    centre_fit_step,
    estimate_sync_lag_s,
    fit_joint_axes,
    fit_joint_centres,
    fit_shank_axis,
    gamma_matrices,
    knee_dips_deg,
    knee_excursion_deg,
    median_principal_axis,
    observable_bias_basis,
    orient_axes,
    orient_thigh_on_gait,
    principal_axis,
    select_fit_samples,
)
from pipeline.params import WALKING, AxesParams
from pipeline.prepare import PreparedLeg
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.walking import build_walking_leg_input, gait_events, orient_on_gait
from tests.pipeline.legs import leg_streams, prepared


def _hinge_gyros(seed: int, n: int = 3000, fs: float = 100.0):
    """Thigh and shank angular velocities (segment frames, y = knee axis) of a gait-like hinge motion plus
    out-of-plane thigh rotation, expressed in randomly mounted sensor frames."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    # gait-like: the shank has large positive (mid-swing) peaks and a moderate negative stance phase; the thigh
    # swings with it
    shank_rate = 6.0 * np.maximum(np.cos(2 * np.pi * t), 0) ** 2 - 1.2
    thigh_rate = 1.5 * np.cos(2 * np.pi * t - 0.4)
    knee_rate = thigh_rate - shank_rate
    out_of_plane = np.column_stack([0.4 * np.sin(2 * np.pi * 0.5 * t), 0 * t, 0.3 * np.cos(2 * np.pi * 0.3 * t)])
    w_thigh = out_of_plane + np.column_stack([0 * t, thigh_rate, 0 * t])
    w_shank = out_of_plane + np.column_stack([0 * t, shank_rate, 0 * t])
    r1 = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    r2 = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    g1 = w_thigh @ r1 + 0.01 * rng.standard_normal((n, 3))  # sensor = segment @ R (R maps sensor->segment)
    g2 = w_shank @ r2 + 0.01 * rng.standard_normal((n, 3))
    y = np.array([0.0, 1.0, 0.0])
    return g1, g2, r1.T @ y, r2.T @ y, knee_rate


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_axis_fit_recovers_the_hinge_axis_for_any_mounting(seed: int) -> None:
    g1, g2, j1_true, j2_true, knee_rate = _hinge_gyros(seed)
    ax = fit_joint_axes(g1, g2)
    assert abs(ax.j1 @ j1_true) > 0.999
    assert abs(ax.j2 @ j2_true) > 0.999
    # sign convention: flexion rate g1.j1 - g2.j2 equals the true knee rate (not its negative)
    rate = g1 @ ax.j1 - g2 @ ax.j2
    assert np.corrcoef(rate, knee_rate)[0, 1] > 0.99


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_shank_axis_fitted_against_a_given_thigh_axis(seed: int) -> None:
    g1, g2, j1_true, j2_true, _ = _hinge_gyros(seed)
    start = Rotation.from_rotvec(np.radians(30.0) * np.array([1.0, 0.0, 0.0])).apply(j2_true)
    j2, rms = fit_shank_axis(g1, g2, j1_true, start)
    assert axis_angle_deg(j2, j2_true) < 0.2
    assert rms < 2.0  # deg/s: the gyro noise, not a misfit
    _, rms_off = fit_shank_axis(g1, g2, Rotation.from_euler("z", 10.0, degrees=True).apply(j1_true), start)
    assert rms_off > 2 * rms


def test_the_thigh_axis_of_many_cycles_is_not_tilted_by_a_few_turns() -> None:
    """Cycles rotating about one axis (different amplitudes, noise), three of them also turning about another at
    4 rad/s (a sharp turn while running): the pooled principal axis leans towards the turn, the median over the
    cycles does not."""
    rng = np.random.default_rng(4)
    axis = np.array([0.2, 0.9, -0.3]) / np.linalg.norm([0.2, 0.9, -0.3])
    turn = np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
    t = np.arange(80) / 200.0
    rows, runs = [], []
    for k in range(20):
        yaw = 4.0 * turn if k in (6, 7, 8) else np.zeros(3)
        swing = rng.uniform(4.0, 6.0) * np.sin(2 * np.pi * 2.5 * t)[:, None] * axis
        rows.append(swing + yaw + 0.05 * rng.standard_normal((t.size, 3)))
        runs.append((k * t.size, (k + 1) * t.size))
    g = np.concatenate(rows)
    assert axis_angle_deg(principal_axis(g), axis) > 1.0
    assert axis_angle_deg(median_principal_axis(g, runs), axis) < 0.2
    assert axis_angle_deg(median_principal_axis(g, runs[:2]), principal_axis(g[:2 * t.size])) < 1e-9


def test_sign_convention_is_independent_of_the_initial_signs() -> None:
    g1, g2, j1_true, j2_true, _ = _hinge_gyros(5)
    for s1 in (1, -1):
        for s2 in (1, -1):
            j1, j2 = orient_axes(s1 * j1_true, s2 * j2_true, g1, g2)
            w2 = g2 @ j2
            assert np.percentile(w2, 99.5) > -np.percentile(w2, 0.5)
            assert np.corrcoef(g1 @ j1, w2)[0, 1] > 0


def test_thigh_sign_on_gait_ignores_counter_rotating_movements() -> None:
    """Inside strides thigh and shank swing together; a squat outside them (opposite senses, larger rates) must not
    decide the sign of j1."""
    g1, g2, j1_true, j2_true, _ = _hinge_gyros(5)
    n = g1.shape[0]
    squat = np.zeros(n, dtype=bool)
    squat[: n // 2] = True
    w = 5.0 * np.sin(np.arange(n) / 10.0)
    g1 = g1.copy()
    g2 = g2.copy()
    g1[squat] = np.outer(w[squat], j1_true)
    g2[squat] = np.outer(-w[squat], j2_true)
    strides = [(n // 2 + 10, n // 2 + 50, n - 10)]
    _, j2 = orient_axes(j1_true, j2_true, g1[~squat], g2[~squat])
    for s1 in (1, -1):
        j1 = orient_thigh_on_gait(s1 * j1_true, j2, g1, g2, strides, 100.0)
        gait = ~squat
        assert np.corrcoef(g1[gait] @ j1, g2[gait] @ j2)[0, 1] > 0
    # the whole-session rule is fooled by the squat
    j1_all, _ = orient_axes(j1_true, j2, g1, g2)
    assert np.corrcoef(g1[~squat] @ j1_all, g2[~squat] @ j2)[0, 1] < 0


def test_fit_sample_set_is_bounded_and_spread() -> None:
    n = 50_000
    rng = np.random.default_rng(0)
    g = rng.standard_normal((n, 3))
    idx = select_fit_samples(g, g, np.ones(n, dtype=bool), AxesParams(max_fit_samples=2000, fit_chunks=20))
    assert idx.size <= 2000
    counts, _ = np.histogram(idx, bins=20, range=(0, n))
    assert counts.min() > 0


def test_accelerometer_angle_on_exact_planar_kinematics() -> None:
    """Two segments hinged about y, gravity only, sensors on the segment axes: Eq. 6-7 gives the knee angle."""
    fs = 100.0
    t = np.arange(0, 4, 1 / fs)
    knee = np.deg2rad(30 + 25 * np.sin(2 * np.pi * t))
    thigh = np.deg2rad(10 * np.sin(2 * np.pi * 0.5 * t))
    shank = thigh - knee

    def spec_force(theta: np.ndarray) -> np.ndarray:
        # segment frame: x forward, z up along the segment; segment pitched by theta about y (distal end forward)
        return 9.81 * np.column_stack([-np.sin(theta), 0 * theta, np.cos(theta)])

    w1 = np.column_stack([0 * t, np.gradient(thigh, 1 / fs), 0 * t])
    a1, a2 = spec_force(thigh), spec_force(shank)
    j = np.array([0.0, 1.0, 0.0])
    # sensors sit on the axes: thigh sensor above the knee (o1 = +z), shank sensor below (o2 = -z)
    centres = JointCentres(o1=np.array([0, 0, 1e-3]) * 100, o2=np.array([0, 0, -1e-3]) * 100,
                           rms_residual_mps2=0.0, absolute=True)
    zero = np.zeros_like(w1)
    ang = accelerometer_angle_deg(a1, zero, zero, a2, zero, zero, j, j, centres)
    assert np.corrcoef(ang, np.rad2deg(knee))[0, 1] > 0.999
    assert np.max(np.abs(ang - np.rad2deg(knee))) < 0.5
    gd = angular_acceleration(w1, fs)
    np.testing.assert_allclose(gd[5:-5, 1], np.gradient(w1[:, 1], 1 / fs)[5:-5], atol=0.05)


def test_sync_lag_from_the_hinge_constraint() -> None:
    """Shank samples delayed by 3 samples (30 ms at 100 Hz): the Eq. 2 magnitudes line up again at that lag."""
    g1, g2, j1, j2, _ = _hinge_gyros(7, n=6000)
    lag = 3
    g2_late = np.vstack([g2[:lag], g2[:-lag]])  # shank events appear 3 samples late
    est = estimate_sync_lag_s(g1, g2_late, j1, j2, np.ones(g1.shape[0], dtype=bool), 100.0)
    assert est is not None and abs(est - 0.03) < 0.004
    assert abs(estimate_sync_lag_s(g1, g2, j1, j2, np.ones(g1.shape[0], dtype=bool), 100.0)) < 0.004


def test_sync_lag_is_none_without_out_of_plane_motion() -> None:
    t = np.arange(3000) / 100.0
    g1 = np.column_stack([0 * t, np.cos(2 * np.pi * t), 0 * t])
    g2 = np.column_stack([0 * t, 3 * np.cos(2 * np.pi * t + 1), 0 * t])
    j = np.array([0.0, 1.0, 0.0])
    assert estimate_sync_lag_s(g1, g2, j, j, np.ones(t.size, dtype=bool), 100.0) is None


def _in_plane_centre_errors_cm(sim, params) -> list[float]:
    """|fitted - true| sensor positions in the joint plane [cm], thigh and shank of both legs."""
    out = []
    for leg in ("left", "right"):
        thigh = next(s for s in sim.streams if s.leg == leg and s.segment == "thigh")
        shank = next(s for s in sim.streams if s.leg == leg and s.segment == "shank")
        synced = synchronised_leg(leg, thigh, shank, params)
        data = build_walking_leg_input(synced.prep, params, synced.axes, fit_gyr=synced.fit_gyr,
                                       thigh_fit=synced.thigh_fit)
        c = data.centres
        if params.axes.centre_bias_prior_mps2 == 0:
            assert not c.b1.any() and not c.b2.any()
        for seg, o, j in (("thigh", c.o1, data.axes.j1), ("shank", c.o2, data.axes.j2)):
            info = sim.info["sensors"][f"{leg[0].upper()}-{seg}"]
            true_o = np.array(info["mounting"]).T @ np.array(info["lever_arm_m"])
            d = o - true_o
            out.append(100 * float(np.linalg.norm(d - (d @ j) * j)))
    return out


@pytest.mark.parametrize("seed", [1, 3])
def test_accelerometer_bias_in_the_centre_fit(seed: int) -> None:
    """Accelerometer biases of 0.03 g pull the Eq. 5 centres centimetres off in the joint plane when the fit ignores
    them; fitted as nuisance parameters (prior 0.03 g; off by default, see ``AxesParams.centre_bias_prior_mps2``),
    the centres stay within ~1 cm (sit-to-stand tilts the segments against gravity, which makes the in-plane
    biases observable)."""
    sim = simulate_session(SimConfig(seed=seed, duration_s=60.0, bout_strides=10, activities=("sit_to_stand",),
                                     acc_bias_ms2=0.3, sync_offset_ms=0.0, clock_drift_ppm=0.0))
    # the biases left in the accelerometers (the rest offset of preparation would remove most of them)
    raw = dataclasses.replace(WALKING, posture=dataclasses.replace(WALKING.posture, rest_offset_max_mps2=0.0))
    on = dataclasses.replace(raw, axes=dataclasses.replace(WALKING.axes, centre_bias_prior_mps2=0.3))
    off = dataclasses.replace(raw, axes=dataclasses.replace(WALKING.axes, centre_bias_prior_mps2=0.0))
    with_bias, without = _in_plane_centre_errors_cm(sim, on), _in_plane_centre_errors_cm(sim, off)
    assert max(without) > 3.0  # the case shows the problem
    assert max(with_bias) < 1.5


_BIAS_ON = dataclasses.replace(WALKING.axes, centre_bias_prior_mps2=0.3)


def _tilted_legs(together: bool, seed: int = 0, n: int = 2000, bias_mps2: float = 0.3):
    """Accelerometers tilted about the knee axis z through a sit-to-stand range and turning slowly about it (one
    tilt and rate per block of 50 samples), the shank on its own or rigidly with the thigh; each sensor 10-20 cm
    from the knee centre, with a constant bias (0.3 m/s^2 per axis) and noise. Returns (a1, g1, a2, g2, true biases)."""
    rng = np.random.default_rng(seed)
    th1, w1 = np.repeat(rng.uniform(-0.3, 1.6, 40), n // 40), np.repeat(rng.uniform(-2.0, 2.0, 40), n // 40)
    th2, w2 = (th1, w1) if together else (np.repeat(rng.uniform(-1.6, 0.3, 40), n // 40),
                                          np.repeat(rng.uniform(-2.0, 2.0, 40), n // 40))
    z = np.zeros(n)
    g1, g2 = np.column_stack([z, z, w1]), np.column_stack([z, z, w2])
    o1, o2 = np.array([0.02, 0.15, 0.03]), np.array([-0.01, -0.12, 0.04])
    b1, b2 = bias_mps2 * rng.standard_normal(3), bias_mps2 * rng.standard_normal(3)
    a1, a2 = (9.81 * np.column_stack([np.cos(th), np.sin(th), z]) + gamma_matrices(g, 0 * g) @ o + b
              + 0.05 * rng.standard_normal((n, 3)) for th, g, o, b in ((th1, g1, o1, b1), (th2, g2, o2, b2)))
    return a1, g1, a2, g2, np.concatenate([b1, b2])


@pytest.mark.parametrize("together", [False, True])
def test_only_observable_bias_directions_are_fitted(together: bool) -> None:
    """Eq. 5 with biases sees ``b1.u1 - b2.u2`` (u_i: gravity in sensor i). Tilting about the knee axis z leaves the
    z components unseen; a leg moving rigidly (u1 = u2) leaves the part common to both unseen as well. The fitted
    subspace must hold exactly what the data see: 4 in-plane directions, or 2 (the in-plane difference b1 - b2), and
    the fitted biases must match the true ones in it."""
    a1, g1, a2, g2, b_true = _tilted_legs(together)
    z = np.array([0.0, 0.0, 1.0])
    off = fit_joint_centres(a1, g1, 0 * g1, a2, g2, 0 * g2, z, z, WALKING.axes)
    m1, m2 = gamma_matrices(g1, 0 * g1), gamma_matrices(g2, 0 * g2)
    basis = observable_bias_basis(np.concatenate([off.o1, off.o2]), a1, m1, a2, m2, _BIAS_ON)
    assert basis.shape == (6, 2 if together else 4)
    # nothing along the axis (up to the tilt of u_i by the biases themselves, ~|b| / g)
    unseen = np.eye(6)[[2, 5]]
    if together:
        unseen = np.vstack([unseen, np.array([[1, 0, 0, 1, 0, 0], [0, 1, 0, 0, 1, 0]]) / np.sqrt(2)])
    assert np.abs(unseen @ basis).max() < 0.1
    c = fit_joint_centres(a1, g1, 0 * g1, a2, g2, 0 * g2, z, z, _BIAS_ON)
    b_fit = np.concatenate([c.b1, c.b2])
    assert np.abs(unseen @ b_fit).max() < 0.05  # held at 0 where unseen, whatever the true bias there
    assert np.abs(basis.T @ (b_fit - b_true)).max() < 0.03
    assert np.abs(unseen @ b_true).max() > 0.1  # the case shows it


def test_biases_the_prior_calls_implausible_are_dropped() -> None:
    """Fitted biases of ~10 prior SDs are not what the prior describes (the prior-predictive check in
    :func:`pipeline.axes.fit_joint_centres`): the fit keeps the bias-free centres rather than such biases."""
    a1, g1, a2, g2, _ = _tilted_legs(False, bias_mps2=3.0)
    z = np.array([0.0, 0.0, 1.0])
    c = fit_joint_centres(a1, g1, 0 * g1, a2, g2, 0 * g2, z, z, _BIAS_ON)
    off = fit_joint_centres(a1, g1, 0 * g1, a2, g2, 0 * g2, z, z, WALKING.axes)
    assert not c.b1.any() and not c.b2.any()
    assert np.allclose(c.o1, off.o1) and np.allclose(c.o2, off.o2)
    loose = dataclasses.replace(_BIAS_ON, centre_bias_check_level=1.0)
    assert np.abs(fit_joint_centres(a1, g1, 0 * g1, a2, g2, 0 * g2, z, z, loose).b1).max() > 1.0  # the check acts


def test_sync_lag_search_follows_a_given_centre() -> None:
    """A 90 ms lag lies outside the +-60 ms searched around zero (no interior minimum: None) and is found when the
    search is centred near it (a drifting lag followed from window to window)."""
    fs, n = 100.0, 3000
    t = np.arange(n) / fs
    rng = np.random.default_rng(3)
    # out-of-plane motion of a hinge in both segments: a broadband rate about an axis perpendicular to the hinge
    base = np.convolve(rng.standard_normal(n + 40), np.ones(20) / 20, mode="same")[20:20 + n]
    g1 = np.column_stack([base, np.sin(2 * np.pi * t), np.zeros(n)])
    late = np.interp(t - 0.09, t, base)
    g2 = np.column_stack([late, np.sin(2 * np.pi * (t - 0.09)), np.zeros(n)])
    j = np.array([0.0, 1.0, 0.0])
    valid = np.ones(n, dtype=bool)
    assert estimate_sync_lag_s(g1, g2, j, j, valid, fs, max_lag_s=0.06) is None
    lag = estimate_sync_lag_s(g1, g2, j, j, valid, fs, max_lag_s=0.06, centre_s=0.07)
    assert lag is not None and abs(lag - 0.09) < 0.002


@pytest.mark.parametrize("holes", [False, True])
def test_lag_search_memory_stays_that_of_the_window(holes: bool) -> None:
    """A 53 s clock window (the longest `clock_model` cuts) at 2000 Hz searches 241 lags: comparing them one at a time
    keeps the search within a few copies of the window (as one (lags, samples) matrix it peaked at ~390 MB)."""
    import tracemalloc

    fs = 2000.0
    rng = np.random.default_rng(0)
    m1, m2 = rng.standard_normal(int(160 * fs)), rng.standard_normal(int(160 * fs))
    valid = np.ones(m1.size, dtype=bool)
    if holes:
        valid[::5000] = False
    still = np.zeros((m1.size, 3))
    j = np.array([0.0, 0.0, 1.0])
    tracemalloc.start()
    try:
        estimate_sync_lag_s(still, still, j, j, valid, fs, window=slice(0, int(53.3 * fs)), rates=(m1, m2),
                            max_lag_s=0.06)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6


def test_the_centre_fit_samples_span_the_same_stretch_of_gait_at_any_rate() -> None:
    # one gait-like signal sampled at 100 and 200 Hz: the centre fit's budget covers the same time at both rates
    assert [centre_fit_step(fs) for fs in (40.0, 50.0, 100.0, 128.0, 200.0, 400.0)] == [1, 1, 1, 1, 2, 4]
    spans = {}
    for fs in (100.0, 200.0):
        t = np.arange(0, 120, 1 / fs)
        g = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * 0.9 * t), 0.1 * t], axis=1)
        idx = select_fit_samples(g, g, np.ones(t.size, dtype=bool), step=centre_fit_step(fs))
        assert idx.size <= WALKING.axes.max_fit_samples and np.all(idx % centre_fit_step(fs) == 0)
        spans[fs] = len(np.unique(np.round(t[idx], 1)))  # distinct tenths of a second taken
    assert spans[200.0] >= 0.9 * spans[100.0]
    # without the step, 200 Hz bunches its budget into about half the time
    t = np.arange(0, 120, 1 / 200.0)
    g = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * 0.9 * t), 0.1 * t], axis=1)
    dense = select_fit_samples(g, g, np.ones(t.size, dtype=bool))
    assert len(np.unique(np.round(t[dense], 1))) < 0.8 * spans[100.0]


def _walk_angles(thigh_amp_deg: float, thigh_peak_phase: float
                 ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """20 strides of 1.1 s at 100 Hz: ``fs``, time (N,) [s], the thigh's angle (a cosine of ``thigh_amp_deg`` peaking
    at ``thigh_peak_phase`` of the cycle) and the knee's (a loading bump and a 60 deg swing peak at 72 %) [deg], and
    the heel-strike indices."""
    fs, stride_s = 100.0, 1.1
    t = np.arange(int(fs * stride_s * 20)) / fs
    phase = (t / stride_s) % 1.0
    thigh = thigh_amp_deg * np.cos(2 * np.pi * (phase - thigh_peak_phase))
    knee = 60 * np.exp(-(((phase - 0.72) / 0.09) ** 2)) + 15 * np.exp(-(((phase - 0.15) / 0.07) ** 2))
    return fs, t, thigh, knee, np.arange(0, t.size, int(fs * stride_s))


def test_thigh_sign_follows_the_segments_angles_not_their_rates() -> None:
    """Thigh and shank ANGLES co-vary in gait (both most forward at heel strike): the thigh's sign follows them even
    when opposed high-frequency motion (soft tissue, ringing after heel strike) makes the RATES anti-correlated, which
    flipped the thigh of some legs on an independent simulator (a knee read as the sum of the segments' angles)."""
    fs, t, thigh, knee, hs = _walk_angles(20.0, 0.87)
    phase = (t / 1.1) % 1.0
    ring = 600 * np.sin(2 * np.pi * 12 * t) * np.exp(-phase / 0.1)
    w1 = np.gradient(thigh) * fs + ring
    w2 = np.gradient(thigh - knee) * fs - ring
    assert np.corrcoef(w1, w2)[0, 1] < 0  # the rates alone would flip the thigh
    j = np.array([0.0, 0.0, 1.0])
    g1, g2 = np.outer(np.radians(w1), j), np.outer(np.radians(w2), j)
    strides = [(int(a), int(a) + 60, int(b)) for a, b in zip(hs[:-1], hs[1:], strict=True)]
    assert np.array_equal(orient_thigh_on_gait(j, j, g1, g2, strides, fs), j)
    assert np.array_equal(orient_thigh_on_gait(-j, j, g1, g2, strides, fs), j)


def test_thigh_sign_holds_with_a_stiff_hip() -> None:
    """A hip that moves +-10 deg, its flexion late (hip osteoarthritis, a walker): the thigh's and the shank's angles
    then co-vary NEGATIVELY, so a rule that asks them to co-vary flipped the thigh (a knee read as the sum of the
    segments' angles, 20 deg below its mid-stance value at heel strike). The knee's dip below mid-stance decides."""
    fs, _, thigh, knee, hs = _walk_angles(10.0, 0.8)
    assert np.corrcoef(thigh, thigh - knee)[0, 1] < -0.05
    j = np.array([0.0, 1.0, 0.0])
    g1, g2 = np.outer(np.radians(np.gradient(thigh) * fs), j), np.outer(np.radians(np.gradient(thigh - knee) * fs), j)
    strides = [(int(a), int(a) + 66, int(b)) for a, b in zip(hs[:-1], hs[1:], strict=True)]
    for start in (j, -j):
        assert np.array_equal(orient_thigh_on_gait(start, j, g1, g2, strides, fs), j)
    right, wrong = knee_dips_deg(g1 @ j, g2 @ j, strides, fs)
    assert np.median(right) < 5.0 < 15.0 < np.median(wrong)


def test_sensors_left_lying_off_the_body_do_not_level_the_knee_axes() -> None:
    """The left leg's sensors lie still for the second half of the session, the knee axis pointing up (gravity along
    it): the session's mean specific force is no longer the body's up, the hinge would lean far out of its plane,
    and levelling towards it put the strides' peaks ~25 deg low on an independent simulator. Such a lean keeps the
    hinge as fitted (AxesParams.max_level_lean_deg), and the strides before the sensors came off stay right. The leg
    is processed alone: beside a walking right leg the session cuts the still half out first (pipeline.worn)."""
    import dataclasses

    from pipeline.session import process_session
    from pipeline.simulate import SimConfig, simulate_session

    sim = simulate_session(SimConfig(seed=2, duration_s=120.0, bout_strides=12, activities=("standing",)))
    clean = process_session(sim.streams).legs["left"].diagnostics
    rng = np.random.default_rng(0)
    half = sim.duration_s / 2
    streams = []
    for s in sim.streams:
        if s.leg == "left":
            off = s.t_s > half
            axis = np.asarray(clean.j1 if s.segment == "thigh" else clean.j2)
            gyr, acc = s.gyr.copy(), s.acc.copy()
            gyr[off] = 0.3 * rng.standard_normal((int(off.sum()), 3))
            acc[off] = 9.81 * axis + 0.05 * rng.standard_normal((int(off.sum()), 3))
            s = dataclasses.replace(s, gyr=gyr, acc=acc)
        streams.append(s)
    left = process_session([s for s in streams if s.leg == "left"]).legs["left"]
    assert max(left.diagnostics.hinge_lean_deg) > WALKING.axes.max_level_lean_deg
    assert not left.diagnostics.knee_axes_levelled
    truth = {round(t.t_start_s, 1): t.peak_swing_flexion_deg for t in sim.truth["left"].strides if t.steady}
    errs = [s.peak_swing_flexion_deg - min(truth.items(), key=lambda kv: abs(kv[0] - s.t_start_s))[1]
            for s in left.strides if s.t_end_s < half and s.quality >= 0.5]
    assert len(errs) >= 10 and np.median(np.abs(errs)) < 3.0


def _leg_prep(seed: int, leg: str) -> tuple[PreparedLeg, np.ndarray, np.ndarray, JointAxes]:
    return prepared(*leg_streams(simulate_session(SimConfig(seed=seed, duration_s=60.0)).streams, leg))


@pytest.mark.parametrize(("seed", "leg"), [(0, "left"), (2, "right"), (5, "right"), (0, "right")])
def test_both_axes_turned_round_are_turned_back_by_gait(seed: int, leg: str) -> None:
    """The axes' common sign from gait (pipeline.walking.orient_on_gait): given both axes turned round (what the
    largest-excursion rule does where a shank turns back faster in early swing than it swings forwards, as in the
    trailing leg of step-to gait), the knee flexes below its extension over the strides that sign finds and the
    turned sign is taken back; the right sign is kept."""
    prep, g1, g2, axes = _leg_prep(seed, leg)
    assert orient_on_gait(prep, axes, g1, g2, WALKING) is axes
    wrong = dataclasses.replace(axes, j1=-axes.j1, j2=-axes.j2)
    assert len(gait_events(prep, wrong, WALKING)[1].strides) >= WALKING.axes.sign_min_strides  # (0, right): two
    back = orient_on_gait(prep, wrong, g1, g2, WALKING)
    assert np.allclose(back.j1, axes.j1) and np.allclose(back.j2, axes.j2)
    strides = gait_events(prep, axes, WALKING)[1].strides
    right = knee_excursion_deg(g1 @ axes.j1, g2 @ axes.j2, strides, prep.fs_hz)
    assert right is not None and np.median(right) > 15.0
    negated = knee_excursion_deg(-g1 @ axes.j1, -g2 @ axes.j2, strides, prep.fs_hz)
    assert negated is not None and np.allclose(negated, -right)


def test_a_sign_that_finds_no_gait_is_not_judged() -> None:
    """Where the given sign finds fewer than ``sign_min_strides`` strides, the other is not taken for it, however
    gait-like its strides (a step test alone: the other sign's three strides would anchor a trace 12 deg off)."""
    prep, g1, g2, axes = _leg_prep(1, "left")
    wrong = dataclasses.replace(axes, j1=-axes.j1, j2=-axes.j2)
    assert len(gait_events(prep, wrong, WALKING)[1].strides) < WALKING.axes.sign_min_strides
    assert orient_on_gait(prep, wrong, g1, g2, WALKING) is wrong
