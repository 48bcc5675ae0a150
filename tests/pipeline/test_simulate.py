"""Physics and bookkeeping checks of the IMU simulator (pipeline/simulate.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.simulate import GRAVITY_MS2, SimConfig, SimSession, gilbert_elliott_losses, simulate_session

CLEAN = dict(gyro_noise_dps=0.0, gyro_bias_dps=0.0, gyro_bias_walk_dps=0.0, acc_noise_ms2=0.0, acc_bias_ms2=0.0,
             impact_level=0.0, wobble_level=0.0, packet_loss=0.0, outages_per_min=0.0, sync_offset_ms=0.0,
             clock_drift_ppm=0.0)


def _stream(sim: SimSession, sid: str):
    return next(s for s in sim.streams if s.sensor_id == sid)


def _knee_from_gyro(sim: SimSession, leg: str) -> tuple[np.ndarray, np.ndarray]:
    """Integrate the relative sagittal angular velocity (segment y axis) into a knee angle, degrees."""
    p = leg[0].upper()
    th, sh = _stream(sim, f"{p}-thigh"), _stream(sim, f"{p}-shank")
    mounts = sim.info["sensors"]
    w_th = th.gyr @ np.array(mounts[f"{p}-thigh"]["mounting"]).T  # sensor -> segment frame
    w_sh = sh.gyr @ np.array(mounts[f"{p}-shank"]["mounting"]).T
    t = th.t_s
    w_sh_y = np.interp(t, sh.t_s, w_sh[:, 1])
    rate = w_sh_y - w_th[:, 1]
    angle = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t))])
    return t, angle + sim.truth[leg].angle_at(t[:1])[0]


@pytest.fixture(scope="module")
def clean_sim() -> SimSession:
    return simulate_session(SimConfig(pattern="normal", fs_hz=200, seed=3, n_strides=16, bout_strides=8,
                                      activities=("sitting",), **CLEAN))


@pytest.mark.parametrize("mounting", ["aligned", "random"])
def test_integrated_relative_gyro_reproduces_true_knee_angle(mounting: str) -> None:
    sim = simulate_session(SimConfig(pattern="fast", fs_hz=200, seed=5, n_strides=10, mounting=mounting, **CLEAN))
    for leg in ("left", "right"):
        t, est = _knee_from_gyro(sim, leg)
        err = est - sim.truth[leg].angle_at(t)
        assert np.sqrt(np.mean(err**2)) < 0.2
        assert np.abs(err).max() < 0.6


def test_accelerometer_reads_gravity_at_rest(clean_sim: SimSession) -> None:
    for s in clean_sim.streams:
        quiet = s.t_s < 1.5  # every session starts with quiet standing
        norms = np.linalg.norm(s.acc[quiet], axis=1)
        assert quiet.sum() > 100
        assert np.allclose(norms, GRAVITY_MS2, atol=0.05)
        # and during walking it does not (impacts are off: this is the leg's own acceleration)
        assert np.linalg.norm(s.acc, axis=1).std() > 1.0


def test_sitting_bends_knee_to_about_90_degrees(clean_sim: SimSession) -> None:
    angle = clean_sim.truth["left"].angle_deg
    assert 85 < angle.max() < 95
    # the thigh is horizontal while seated, so gravity lies in its sagittal plane, off its long axis
    assert np.abs(angle - 90).min() < 2


def test_mounting_rotation_preserves_norms_and_changes_axes() -> None:
    base = SimConfig(pattern="normal", seed=11, n_strides=6, **CLEAN)
    a = simulate_session(dataclasses.replace(base, mounting="aligned"))
    r = simulate_session(dataclasses.replace(base, mounting="random"))
    for sa, sr in zip(a.streams, r.streams, strict=True):
        assert np.allclose(sa.t_s, sr.t_s)
        assert np.allclose(np.linalg.norm(sa.gyr, axis=1), np.linalg.norm(sr.gyr, axis=1), atol=1e-6)
        assert np.allclose(np.linalg.norm(sa.acc, axis=1), np.linalg.norm(sr.acc, axis=1), atol=1e-6)
        assert np.abs(sa.gyr - sr.gyr).max() > 10.0
        m = np.array(r.info["sensors"][sr.sensor_id]["mounting"])
        assert np.allclose(m @ m.T, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(m), 1.0)


def test_right_mounting_mirrors_left() -> None:
    sim = simulate_session(SimConfig(seed=2, n_strides=4, **CLEAN))
    mirror = np.diag([1.0, -1.0, 1.0])
    for seg in ("thigh", "shank"):
        left = np.array(sim.info["sensors"][f"L-{seg}"]["mounting"])
        right = np.array(sim.info["sensors"][f"R-{seg}"]["mounting"])
        rel = (mirror @ left @ mirror).T @ right  # the small random placement difference
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
        assert angle <= 10.0 + 1e-6


def test_truth_events_are_ordered_and_legs_alternate() -> None:
    sim = simulate_session(SimConfig(pattern="normal", seed=4, n_strides=30))
    hs = {leg: sim.truth[leg].heel_strikes_s for leg in ("left", "right")}
    for leg in ("left", "right"):
        tr = sim.truth[leg]
        assert np.all(np.diff(tr.heel_strikes_s) > 0.5)
        assert len(tr.strides) >= 20
        for s in tr.strides:
            assert s.t_start_s < s.t_toe_off_s < s.t_end_s
            assert 0.55 < (s.t_toe_off_s - s.t_start_s) / (s.t_end_s - s.t_start_s) < 0.65
            assert s.min_flexion_deg <= s.stance_flexion_deg
            assert not s.steady or s.stance_flexion_deg <= s.peak_swing_flexion_deg
            assert s.rom_deg >= s.peak_swing_flexion_deg - s.min_flexion_deg - 1e-9
            if s.steady:  # the swing peak is the stride's maximum
                assert np.isclose(s.rom_deg, s.peak_swing_flexion_deg - s.min_flexion_deg, atol=0.5)
            assert s.peak_swing_flexion_deg == pytest.approx(
                tr.angle_deg[(tr.t_s >= s.t_toe_off_s) & (tr.t_s <= s.t_end_s)].max(), abs=1e-9)
    # a right heel strike lies between consecutive left heel strikes of a steady stride
    for s in sim.truth["left"].strides:
        if s.steady:
            inside = hs["right"][(hs["right"] > s.t_start_s) & (hs["right"] < s.t_end_s)]
            assert len(inside) == 1
            assert 0.4 < (inside[0] - s.t_start_s) / (s.t_end_s - s.t_start_s) < 0.6


@pytest.mark.parametrize(("pattern", "peak", "min_", "stance"), [
    ("normal", (55, 70), (0, 8), (0.58, 0.62)),
    ("stiff-knee", (33, 42), (0, 10), (0.6, 0.64)),
    ("crouch", (50, 65), (20, 30), (0.6, 0.64)),
    ("running", (90, 120), (5, 30), (0.35, 0.40)),
])
def test_pattern_characteristics(pattern: str, peak: tuple, min_: tuple, stance: tuple) -> None:
    sim = simulate_session(SimConfig(pattern=pattern, seed=7, n_strides=16, legs=("left",)))
    st = [s for s in sim.truth["left"].strides if s.steady]
    assert len(st) >= 8
    peaks = np.array([s.peak_swing_flexion_deg for s in st])
    assert peak[0] < np.median(peaks) < peak[1]
    assert 0.3 < peaks.std() < 4.0  # stride-to-stride variability, not a copy
    assert min_[0] < np.median([s.min_flexion_deg for s in st]) < min_[1]
    frac = np.median([(s.t_toe_off_s - s.t_start_s) / (s.t_end_s - s.t_start_s) for s in st])
    assert stance[0] < frac < stance[1]
    assert sim.activity == ("running" if pattern == "running" else "walking")


def test_packet_loss_drops_runs_of_samples() -> None:
    base = SimConfig(seed=8, n_strides=20, fs_hz=100)
    full = simulate_session(dataclasses.replace(base, packet_loss=0.0, outages_per_min=0.0))
    lossy = simulate_session(dataclasses.replace(base, packet_loss=0.1, outages_per_min=10.0))
    for sf, sl in zip(full.streams, lossy.streams, strict=True):
        assert len(sl.t_s) < 0.93 * len(sf.t_s)
        assert np.all(np.diff(sl.t_s) > 0)
        gaps = np.diff(sl.t_s)
        assert gaps.max() > 0.25  # an outage
        assert np.sum(gaps > 1.5 / 100) >= 5
        assert len(sl.t_s) == len(sl.gyr) == len(sl.acc)
        # surviving samples are unchanged: the loss only removes data
        idx = np.searchsorted(sf.t_s, sl.t_s)
        assert np.allclose(sf.t_s[idx], sl.t_s)
        assert np.allclose(sf.gyr[idx], sl.gyr)


def test_sensors_are_not_sample_synchronous() -> None:
    sim = simulate_session(SimConfig(seed=9, n_strides=8, fs_hz=50, clock_drift_ppm=200))
    starts = [s.t_s[0] for s in sim.streams]
    assert len({round(x, 6) for x in starts}) == len(starts)
    drifts = [v["drift_ppm"] for v in sim.info["sensors"].values()]
    assert len(set(drifts)) == len(drifts) and max(abs(d) for d in drifts) > 0


def test_units_are_converted() -> None:
    base = SimConfig(seed=10, n_strides=4)
    a = simulate_session(base)
    b = simulate_session(dataclasses.replace(base, gyro_unit="rad/s", acc_unit="g"))
    for sa, sb in zip(a.streams, b.streams, strict=True):
        assert sb.gyro_unit == "rad/s" and sb.acc_unit == "g"
        assert np.allclose(np.radians(sa.gyr), sb.gyr)
        assert np.allclose(sa.acc / GRAVITY_MS2, sb.acc)


def test_deterministic_per_seed() -> None:
    cfg = SimConfig(pattern="slow", seed=12, n_strides=6)
    a, b = simulate_session(cfg), simulate_session(cfg)
    c = simulate_session(dataclasses.replace(cfg, seed=13))
    for sa, sb in zip(a.streams, b.streams, strict=True):
        assert np.array_equal(sa.t_s, sb.t_s) and np.array_equal(sa.gyr, sb.gyr) and np.array_equal(sa.acc, sb.acc)
    assert np.array_equal(a.truth["left"].angle_deg, b.truth["left"].angle_deg)
    assert not np.array_equal(a.streams[0].gyr[:100], c.streams[0].gyr[:100])


def test_duration_config_and_bad_pattern() -> None:
    sim = simulate_session(SimConfig(seed=1, duration_s=90, legs=("right",)))
    assert 85 <= sim.duration_s <= 100
    assert {s.leg for s in sim.streams} == {"right"} and set(sim.truth) == {"right"}
    assert len(sim.truth["right"].bouts_s) >= 2
    with pytest.raises(ValueError):
        simulate_session(SimConfig(pattern="moonwalk"))


def test_accelerations_agree_at_the_knee_joint_centre() -> None:
    """Rigid-body consistency (the constraint behind Seel et al. 2014 Eq. 5): the specific force carried from each
    sensor to the knee centre with its lever arm, a + w x (w x r) + dw/dt x r, has the same magnitude."""
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=200, seed=14, n_strides=8, **CLEAN))
    at_knee = {}
    for seg in ("thigh", "shank"):
        s = _stream(sim, f"L-{seg}")
        meta = sim.info["sensors"][f"L-{seg}"]
        r = np.array(meta["mounting"]).T @ -np.array(meta["lever_arm_m"])  # sensor -> knee centre, sensor frame
        w = np.radians(s.gyr)
        dw = np.gradient(w, s.t_s, axis=0)
        a = s.acc + np.cross(w, np.cross(w, r)) + np.cross(dw, r)
        at_knee[seg] = (s.t_s, np.linalg.norm(a, axis=1))
    t, thigh = at_knee["thigh"]
    shank = np.interp(t, *at_knee["shank"])
    inner = slice(5, -5)
    diff = (thigh - shank)[inner]
    assert np.sqrt(np.mean(diff**2)) < 0.02
    # the lever-arm terms matter: without them the two magnitudes differ clearly during walking
    raw = np.linalg.norm(_stream(sim, "L-thigh").acc, axis=1) - np.interp(
        t, _stream(sim, "L-shank").t_s, np.linalg.norm(_stream(sim, "L-shank").acc, axis=1))
    assert np.sqrt(np.mean(raw[inner] ** 2)) > 5 * np.sqrt(np.mean(diff**2))


def test_saturation_and_a_shank_at_another_rate() -> None:
    base = SimConfig(pattern="fast", seed=15, n_strides=8)
    free = simulate_session(base)
    sim = simulate_session(dataclasses.replace(base, gyro_range_dps=250.0, acc_range_g=2.0, shank_fs_hz=60.0))
    for s in sim.streams:
        assert np.abs(s.gyr).max() <= 250.0 + 1e-9 and np.abs(s.acc).max() <= 2 * GRAVITY_MS2 + 1e-9
        expected_fs = 60.0 if s.segment == "shank" else 100.0
        assert s.fs_hz == expected_fs
        assert np.median(np.diff(s.t_s)) == pytest.approx(1 / expected_fs, rel=1e-3)
    assert np.abs(_stream(free, "L-shank").gyr).max() > 300.0  # so the clip did something
    assert np.mean(np.abs(_stream(sim, "L-shank").gyr) >= 250.0 - 1e-9) > 0.001


# ---------------------------------------------------------------------------------------------------------------
# Robustness options (bench/robustness.py): each changes one modelling assumption


def _quiet(sim: SimSession, leg: str) -> np.ndarray:
    """True knee angle during the quiet standing before the first bout."""
    tr = sim.truth[leg]
    return tr.angle_deg[(tr.t_s > 0.3) & (tr.t_s < tr.bouts_s[0][0] - 0.8)]


def test_standing_and_seated_flexion_appear_in_the_truth() -> None:
    sim = simulate_session(SimConfig(seed=21, n_strides=16, bout_strides=8, activities=("sitting",),
                                     stand_knee_deg=12.0, stand_knee_right_extra_deg=5.0, sit_knee_deg=70.0, **CLEAN))
    assert np.mean(_quiet(sim, "left")) == pytest.approx(12.0, abs=1.5)
    assert np.mean(_quiet(sim, "right")) == pytest.approx(17.0, abs=1.5)
    assert (sim.truth["left"].stand_knee_deg, sim.truth["right"].stand_knee_deg) == (12.0, 17.0)
    sits = [(a, b) for kind, a, b in sim.info["non_gait_s"] if kind == "sit"]
    assert sits
    for leg in ("left", "right"):
        assert sim.truth[leg].angle_at(np.array([0.5 * (sits[0][0] + sits[0][1])]))[0] == pytest.approx(70, abs=2.5)
    default = simulate_session(SimConfig(seed=21, n_strides=16, bout_strides=8, activities=("sitting",), **CLEAN))
    assert 1.0 < np.mean(_quiet(default, "left")) < 7.0  # drawn from 2-6 deg


def test_knee_curves_shift_and_scale_per_leg() -> None:
    base = SimConfig(seed=22, n_strides=16, bout_strides=8, **CLEAN)
    ref = simulate_session(base)
    mod = simulate_session(dataclasses.replace(base, knee_shift_deg=(-3.0, 4.0), knee_scale=(1.0, 1.2)))
    for leg, shift in (("left", -3.0), ("right", 4.0)):
        pairs = [(a, b) for a, b in zip(ref.truth[leg].strides, mod.truth[leg].strides, strict=True) if a.steady]
        assert len(pairs) >= 8
        mins = np.array([b.min_flexion_deg - a.min_flexion_deg for a, b in pairs])
        assert np.allclose(mins, shift, atol=0.3)  # the scale acts above the curve's minimum
        ratio = np.median([b.rom_deg / a.rom_deg for a, b in pairs])
        assert ratio == pytest.approx(1.0 if leg == "left" else 1.2, abs=0.03)


def test_impact_g_is_the_peak_shock_on_the_shank() -> None:
    base = SimConfig(seed=23, n_strides=6, fs_hz=1000.0, **CLEAN)
    five = simulate_session(dataclasses.replace(base, impact_g=5.0))
    ten = simulate_session(dataclasses.replace(base, impact_g=10.0))
    # same random draws and the same (capped) transient rotation: the difference is 5 g of shock exactly
    for sid, g in (("L-shank", 5.0), ("R-shank", 5.0), ("L-thigh", 1.5)):
        diff = np.linalg.norm(_stream(ten, sid).acc - _stream(five, sid).acc, axis=1) / GRAVITY_MS2
        assert 0.97 * g < diff.max() <= 1.001 * g, sid
        n_hs = len(five.truth[sid[0].replace("L", "left").replace("R", "right")].heel_strikes_s)
        assert np.sum((diff[1:] > 0.5 * g) & (diff[:-1] <= 0.5 * g)) >= n_hs - 1  # one shock per heel strike


def test_lever_arms_scale_and_move_off_axis() -> None:
    base = SimConfig(seed=24, n_strides=4)
    ref = simulate_session(base).info["sensors"]
    mod = simulate_session(dataclasses.replace(base, lever_scale=2.0, lever_offaxis_m=0.05)).info["sensors"]
    for sid, meta in ref.items():
        side = 1.0 if sid.startswith("L") else -1.0
        expected = 2.0 * np.array(meta["lever_arm_m"]) + np.array([0.05, 0.05 * side, 0.0])
        assert np.allclose(mod[sid]["lever_arm_m"], expected)


def _runs(lost: np.ndarray) -> np.ndarray:
    edges = np.diff(np.concatenate([[0], lost.astype(int), [0]]))
    return np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)


def test_gilbert_elliott_loss_has_the_requested_mean_and_bursts() -> None:
    rng = np.random.default_rng(0)
    lost = gilbert_elliott_losses(rng, 200_000, 0.05, 4.0)
    assert lost.mean() == pytest.approx(0.05, abs=0.004)
    assert _runs(lost).mean() == pytest.approx(4.0, rel=0.08)
    independent = rng.random(200_000) < 0.05
    assert _runs(independent).mean() < 1.1  # the contrast: independent loss hardly ever loses two in a row
    assert not gilbert_elliott_losses(rng, 1000, 0.0, 4.0).any()


def test_bursty_loss_in_a_session_is_independent_per_sensor() -> None:
    base = SimConfig(seed=25, duration_s=150, packet_samples=5, outages_per_min=0.0)
    sim = simulate_session(dataclasses.replace(base, loss_model="bursty", packet_loss=0.08, loss_burst_packets=5))
    dropped = []
    for s in sim.streams:
        n_lost = sim.info["sensors"][s.sensor_id]["dropped"]
        dropped.append(n_lost)
        assert 0.04 < n_lost / (n_lost + len(s.t_s)) < 0.13
        holes = np.diff(s.t_s)[np.diff(s.t_s) > 1.5 / s.fs_hz]
        assert np.median(holes) > 3 * 5 / s.fs_hz  # bursts of packets, not single packets
    assert len(set(dropped)) == len(dropped)


def test_non_gait_movements_are_never_strides() -> None:
    sim = simulate_session(SimConfig(seed=26, duration_s=150, bout_strides=8,
                                     activities=("jump", "stairs", "sit_to_stand")))
    kinds = [k for k, _, _ in sim.info["non_gait_s"]]
    assert {"jump", "stairs", "sit"} <= set(kinds) and kinds.count("sit") >= 3
    for leg, tr in sim.truth.items():
        for _, a, b in sim.info["non_gait_s"]:
            assert not any(s.t_start_s < b and s.t_end_s > a for s in tr.strides)
            assert not np.any((tr.heel_strikes_s > a) & (tr.heel_strikes_s < b))
        jump = next((a, b) for k, a, b in sim.info["non_gait_s"] if k == "jump")
        inside = (tr.t_s >= jump[0]) & (tr.t_s <= jump[1])
        assert tr.angle_deg[inside].max() > 60  # the knee really moves: a deep countermovement
        shank = _stream(sim, f"{leg[0].upper()}-shank")
        sel = (shank.t_s >= jump[0]) & (shank.t_s <= jump[1])
        assert np.abs(shank.gyr[sel]).max() > 100  # and the sensors see it
        stairs = next((a, b) for k, a, b in sim.info["non_gait_s"] if k == "stairs")
        inside = (tr.t_s >= stairs[0]) & (tr.t_s <= stairs[1])
        assert tr.angle_deg[inside].max() > 70  # a step-up bends each knee in turn
    assert len(sim.truth["left"].strides) >= 10


def test_more_and_sharper_turns() -> None:
    base = SimConfig(seed=27, n_strides=32, bout_strides=16, activities=("standing",))
    ref = simulate_session(base)
    mod = simulate_session(dataclasses.replace(base, turn_every_bouts=1, turns_per_bout=3, turn_strides=1.0))
    n_ref = sum(s.turning for s in ref.truth["left"].strides)
    n_mod = sum(s.turning for s in mod.truth["left"].strides)
    assert n_ref >= 1 and n_mod >= 2 * n_ref


@pytest.mark.parametrize("swap, expected", [
    ("legs", {"L-thigh": ("right", "thigh"), "L-shank": ("right", "shank"), "R-thigh": ("left", "thigh")}),
    ("thighs", {"L-thigh": ("right", "thigh"), "L-shank": ("left", "shank"), "R-thigh": ("left", "thigh")}),
    ("segments", {"L-thigh": ("left", "shank"), "R-shank": ("right", "thigh")}),
    ("left_segments", {"L-thigh": ("left", "shank"), "L-shank": ("left", "thigh"), "R-shank": ("right", "shank")}),
])
def test_swapped_labels_swap_the_streams(swap: str, expected: dict) -> None:
    base = SimConfig(seed=28, n_strides=4)
    ref = {s.sensor_id: s for s in simulate_session(base).streams}
    sim = simulate_session(dataclasses.replace(base, label_swap=swap))
    labels = {(s.leg, s.segment) for s in sim.streams}
    assert len(labels) == 4  # still one sensor per slot
    for s in sim.streams:
        assert np.array_equal(s.gyr, ref[s.sensor_id].gyr)  # the data is the physical sensor's
        if s.sensor_id in expected:
            assert (s.leg, s.segment) == expected[s.sensor_id]


def test_gain_errors_scale_each_axis_and_change_nothing_else() -> None:
    base = SimConfig(pattern="normal", seed=3, duration_s=20.0, legs=("left",))
    off = simulate_session(base)
    on = simulate_session(dataclasses.replace(base, gyro_gain_sd=0.02, acc_gain_sd=0.02))
    for a, b in zip(off.streams, on.streams, strict=True):
        assert np.array_equal(a.t_s, b.t_s)
        for x, y in ((a.gyr, b.gyr), (a.acc, b.acc)):
            ratio = y / x
            gain = np.median(ratio, axis=0)
            assert np.all(np.abs(gain - 1.0) < 0.1) and np.any(np.abs(gain - 1.0) > 1e-4)
            assert np.allclose(y, x * gain, rtol=1e-9, atol=1e-12)  # one constant gain per axis


def _flat_chain_body(t: np.ndarray, heading: np.ndarray):
    from scipy.interpolate import make_interp_spline

    from pipeline.simulate import _BodySplines

    zero = make_interp_spline(t, np.zeros_like(t), k=5)
    return _BodySplines(heading=make_interp_spline(t, heading, k=5), speed=zero, height=zero)


def test_chain_of_one_flexion_is_the_planar_segment() -> None:
    from scipy.interpolate import make_interp_spline

    from pipeline.simulate import _chain_motion, _segment_motion

    t = np.linspace(0, 2, 1001)
    body = _flat_chain_body(t, 0.8 * np.sin(1.3 * t))
    theta = make_interp_spline(t, 0.6 * np.sin(5 * t) + 0.2, k=5)
    planar = _segment_motion(body, theta, t)
    chain = _chain_motion(body, ((1, make_interp_spline(t, -(0.6 * np.sin(5 * t) + 0.2), k=5)),), t)
    for a, b in zip(planar, chain, strict=True):
        assert np.allclose(a, b, atol=1e-9)


def test_chain_rates_are_the_derivatives_of_its_rotations() -> None:
    """omega = vee(dR/dt R^T) and alpha = d(omega)/dt, by central differences on a 3-D chain of five rotations."""
    from scipy.interpolate import make_interp_spline

    from pipeline.simulate import _chain_motion

    t = np.linspace(0, 2, 2001)
    body = _flat_chain_body(t, 0.5 * np.sin(2 * t))
    rng = np.random.default_rng(1)
    links = tuple((axis, make_interp_spline(t, rng.uniform(0.2, 0.8) * np.sin(rng.uniform(2, 8) * t + k), k=5))
                  for k, axis in enumerate((2, 0, 1, 0, 2)))
    h = 1e-5
    tc = np.linspace(0.3, 1.7, 50)
    rot, om, al = _chain_motion(body, links, tc)
    r_p, om_p, _ = _chain_motion(body, links, tc + h)
    r_m, om_m, _ = _chain_motion(body, links, tc - h)
    skew = (r_p - r_m) / (2 * h) @ np.transpose(rot, (0, 2, 1))
    om_fd = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], -1)
    assert np.abs(om_fd - om).max() < 1e-6 * max(1.0, np.abs(om).max())
    assert np.abs((om_p - om_m) / (2 * h) - al).max() < 1e-4 * max(1.0, np.abs(al).max())
    assert np.abs(om).max() > 1.0 and np.abs(al[:, 0]).max() > 1.0  # a real 3-D motion, not a planar one


def test_3d_hip_and_pelvis_keep_the_knee_a_hinge() -> None:
    """With 3-D hip and pelvis motion but a hinge knee the relative rate about the shared y axis still integrates to
    the true knee angle (so the 3-D chain and its truth agree)."""
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=200, seed=5, n_strides=10, hip_3d=2.0, **CLEAN))
    flat = simulate_session(SimConfig(pattern="normal", fs_hz=200, seed=5, n_strides=10, **CLEAN))
    for leg in ("left", "right"):
        t, est = _knee_from_gyro(sim, leg)
        err = est - sim.truth[leg].angle_at(t)
        assert np.sqrt(np.mean(err**2)) < 0.2
        # the thigh's gyro now sees ab/adduction and rotation: its axes differ from the planar session's
        th3, th2 = _stream(sim, f"{leg[0].upper()}-thigh"), _stream(flat, f"{leg[0].upper()}-thigh")
        n = min(len(th3.gyr), len(th2.gyr))
        assert np.abs(th3.gyr[:n] - th2.gyr[:n]).max() > 10.0
    assert np.allclose(sim.truth["left"].angle_deg, flat.truth["left"].angle_deg, atol=1e-6)


def test_3d_knee_rotates_about_the_shank_with_flexion() -> None:
    """knee_3d: the relative rotation is no longer about one axis: the tibia turns about its own long axis as the knee
    flexes (a few deg per 10 deg), the knee's flexion stays the truth, and the joint centre stays common."""
    cfg = SimConfig(pattern="normal", fs_hz=200, seed=7, n_strides=10, mounting="aligned", knee_3d=1.0,
                    hip_3d=1.0, knee_varus_deg=5.0, **CLEAN)
    sim = simulate_session(cfg)
    th, sh = _stream(sim, "L-thigh"), _stream(sim, "L-shank")
    n = min(len(th.gyr), len(sh.gyr))
    t, est = _knee_from_gyro(sim, "left")
    err = est - sim.truth["left"].angle_at(t)
    assert 0.2 < np.sqrt(np.mean(err**2)) < 5.0  # no longer exact, still the same curve
    axial = sh.gyr[:n, 2] - np.interp(sh.t_s[:n], th.t_s, th.gyr[:, 2])
    flex_rate = np.gradient(sim.truth["left"].angle_at(sh.t_s[:n]), sh.t_s[:n])
    assert np.corrcoef(axial, flex_rate)[0, 1] < -0.5  # internal rotation of a left tibia is about -z (z up)
    peaks = [s.peak_swing_flexion_deg for s in sim.truth["left"].strides if s.steady]
    assert 50 < np.median(peaks) < 75
    for seg in ("thigh", "shank"):  # the knee centre is common to both segments (as in the planar test above)
        meta = sim.info["sensors"][f"L-{seg}"]
        assert np.allclose(np.array(meta["mounting"]), np.eye(3))
    at_knee = {}
    for seg in ("thigh", "shank"):
        s = _stream(sim, f"L-{seg}")
        r = -np.array(sim.info["sensors"][f"L-{seg}"]["lever_arm_m"])
        w = np.radians(s.gyr)
        a = s.acc + np.cross(w, np.cross(w, r)) + np.cross(np.gradient(w, s.t_s, axis=0), r)
        at_knee[seg] = (s.t_s, np.linalg.norm(a, axis=1))
    diff = (at_knee["thigh"][1] - np.interp(at_knee["thigh"][0], *at_knee["shank"]))[5:-5]
    assert np.sqrt(np.mean(diff**2)) < 0.05


def test_thigh_skin_turns_about_the_femur_with_flexion() -> None:
    """thigh_sta_deg: the thigh sensor (not the femur) turns about the femur's long axis as the knee flexes; the
    shank sensor and the truth stay as they are."""
    base = dict(pattern="normal", fs_hz=200, seed=4, n_strides=8, mounting="aligned", hip_3d=1.0, **CLEAN)
    sta = simulate_session(SimConfig(thigh_sta_deg=10.0, **base))
    bone = simulate_session(SimConfig(**base))
    th_sta, th_bone = _stream(sta, "L-thigh"), _stream(bone, "L-thigh")
    extra_z = th_sta.gyr[:, 2] - th_bone.gyr[:, 2]  # aligned mounting: sensor z = the femur's long axis
    flex_rate = np.gradient(sta.truth["left"].angle_at(th_sta.t_s), th_sta.t_s)
    # 10 deg per 60 deg of flexion, outwards (+z for a left thigh)
    assert np.polyfit(flex_rate, extra_z, 1)[0] == pytest.approx(10.0 / 60.0, rel=0.05)
    assert np.array_equal(_stream(sta, "L-shank").gyr, _stream(bone, "L-shank").gyr)
    assert np.array_equal(sta.truth["left"].angle_deg, bone.truth["left"].angle_deg)


def test_an_exercise_session_has_no_walking_and_seated_extensions_straighten_one_knee_at_a_time() -> None:
    cfg = SimConfig(seed=2, walking=False, activities=("seated_extension",), move_reps=2, sit_knee_deg=85.0)
    sim = simulate_session(cfg)
    assert all(not t.strides and not t.bouts_s and not t.heel_strikes_s.size for t in sim.truth.values())
    (kind, t0, t1), = [m for m in sim.info["non_gait_s"] if m[0] == "seated_extension"]
    left, right = (sim.truth[leg] for leg in ("left", "right"))
    first = (left.t_s > t0) & (left.t_s < t0 + 6.5)  # the first repetition: the left knee lifts, the right rests
    assert left.angle_deg[first].min() == pytest.approx(10.0, abs=2.0)
    assert right.angle_deg[first].min() > 80.0
    assert right.angle_at(np.array([t0 + 6.5 + 2.5]))[0] == pytest.approx(10.0, abs=2.0)  # then the right's turn
    assert sim.duration_s > t1


def test_the_joint_centre_rolls_with_flexion() -> None:
    """knee_rollback_mm: only the shank's accelerometer changes, and only as flexion moves its origin: carried to a
    fixed centre the two sensors no longer measure one acceleration, by about the rollback's own acceleration."""
    base = dict(pattern="normal", fs_hz=200, seed=7, n_strides=10, mounting="aligned", **CLEAN)
    rolled = simulate_session(SimConfig(knee_rollback_mm=20.0, **base))
    fixed = simulate_session(SimConfig(**base))
    sh_r, sh_f = _stream(rolled, "L-shank"), _stream(fixed, "L-shank")
    assert np.array_equal(sh_r.gyr, sh_f.gyr)
    assert np.array_equal(_stream(rolled, "L-thigh").acc, _stream(fixed, "L-thigh").acc)
    assert np.array_equal(rolled.truth["left"].angle_deg, fixed.truth["left"].angle_deg)
    extra = np.linalg.norm(sh_r.acc - sh_f.acc, axis=1)
    knee = fixed.truth["left"].angle_at(sh_f.t_s)
    # 20 mm per 90 deg moving with swing rates of ~350 deg/s: centripetal and tangential terms of ~0.3-2 m/s^2
    assert 0.3 < np.percentile(extra, 99) < 5.0
    assert np.median(extra[knee > 40]) > 3 * np.median(extra[knee < 8])
