"""The accelerometer offset from the session's rests (pipeline.rest_offset) on synthetic rests and simulated
sessions with the true offsets known."""

from __future__ import annotations

import dataclasses
import signal
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from pipeline.constants import G_MPS2
from pipeline.params import WALKING
from pipeline.posture import standing_mask
from pipeline.prepare import prepare_leg_si, to_si
from pipeline.rest_offset import block_means, fit_rest_offset, posture_clusters, rest_block_starts, rest_offsets
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.sync import synchronised_leg
from pipeline.types import RawSensorStream
from pipeline.walking import build_walking_leg_input


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _rests(directions: list[np.ndarray], offset: np.ndarray, per_posture: int, rng: np.random.Generator,
           sway_deg: float = 0.0) -> np.ndarray:
    """Rest blocks: gravity along each direction (sensor frame) plus the offset and 0.02 m/s^2 of noise; with
    ``sway_deg``, each block's direction tilts by up to that much while its magnitude stays g (a rotation)."""
    out = []
    for d in directions:
        for _ in range(per_posture):
            tilt = np.radians(sway_deg) * rng.standard_normal(3)
            u = _unit(_unit(d) + tilt)
            out.append(G_MPS2 * u + offset + 0.02 * rng.standard_normal(3))
    return np.asarray(out)


def test_distinct_postures_give_the_whole_offset() -> None:
    rng = np.random.default_rng(1)
    b = np.array([0.6, -0.4, 0.3])
    blocks = _rests([np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0.2])], b, 10, rng)
    assert np.allclose(fit_rest_offset(blocks), b, atol=0.03)


def test_one_posture_fixes_only_the_part_along_gravity() -> None:
    """Quiet standing alone shows how far |a| is from g, nothing across gravity: the fit must not invent that part,
    even when sway tilts the blocks by a few degrees."""
    rng = np.random.default_rng(2)
    up = np.array([0.1, 0.2, 1.0])
    b = np.array([0.5, -0.5, 1.3])
    blocks = _rests([up], b, 40, rng, sway_deg=3.0)
    fit = fit_rest_offset(blocks)
    u = _unit(up)
    assert float(fit @ u) == pytest.approx(float(b @ u), abs=0.05)
    seen = _unit(blocks.mean(axis=0))  # the one direction the data show
    assert np.linalg.norm(fit - (fit @ seen) * seen) < 0.02
    # the corrected magnitude is g: the force test now passes where it failed
    raw = G_MPS2 * u + b
    assert abs(np.linalg.norm(raw) - G_MPS2) > WALKING.posture.force_tol * G_MPS2
    assert abs(np.linalg.norm(raw - fit) - G_MPS2) < 0.03


def test_sway_is_one_posture_and_distinct_postures_are_not() -> None:
    rng = np.random.default_rng(3)
    blocks = _rests([np.array([0, 0, 1.0]), np.array([1.0, 0, 0])], np.zeros(3), 15, rng, sway_deg=3.0)
    means, counts = posture_clusters(blocks)
    assert counts.tolist() == [15, 15]
    assert np.allclose(_unit(means[1]), [1, 0, 0], atol=0.02)


def test_blocks_that_are_not_at_rest_are_left_out_and_an_absurd_offset_is_refused() -> None:
    rng = np.random.default_rng(4)
    b = np.array([0.3, 0.2, -0.4])
    rests = _rests([np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0.2])], b, 10, rng)
    moving = np.array([[3.0, 0.0, 12.5]] * 6)  # still gyro, but 0.3 g of sustained acceleration (a vehicle)
    assert np.allclose(fit_rest_offset(np.vstack([rests, moving])), b, atol=0.05)
    huge = _rests([np.array([0, 0, 1.0]), np.array([1.0, 0, 0])], np.array([4.0, 0.0, 0.0]), 10, rng)
    assert np.allclose(fit_rest_offset(huge), 0.0)
    assert np.allclose(fit_rest_offset(np.zeros((0, 3))), 0.0)


def test_rest_blocks_come_from_still_runs_only() -> None:
    fs = 100.0
    n = 1000
    gyr = np.zeros((n, 3))
    gyr[300:500, 0] = 2.0  # 2 rad/s: moving
    acc = np.tile([0.0, 0.0, G_MPS2], (n, 1))
    acc[300:500] = [5.0, 0.0, 5.0]
    valid = np.ones(n, dtype=bool)
    starts, n_blk = rest_block_starts(gyr, valid, fs)
    blocks = block_means(acc, starts, n_blk)
    assert blocks.shape == (3 + 5, 3)  # 300 still samples -> 3 blocks, 500 -> 5; the moving part none
    assert np.allclose(blocks, [0.0, 0.0, G_MPS2])


def _session(acc_bias: float):
    return simulate_session(SimConfig(pattern="normal", seed=7, duration_s=80.0, bout_strides=12, legs=("left",),
                                      acc_bias_ms2=acc_bias))


def test_prepared_accelerometers_carry_the_offset_removed_and_the_reused_thigh_keeps_its_own() -> None:
    sim = _session(1.0)
    by = {s.segment: s for s in sim.streams}
    true = {seg: np.asarray(sim.info["sensors"][f"L-{seg}"]["acc_bias_mps2"]) for seg in ("thigh", "shank")}
    si1, si2 = to_si(by["thigh"]), to_si(by["shank"])
    prep = prepare_leg_si("left", si1, si2, 100.0, 100.0)
    for seg, off in (("thigh", prep.acc_offset_thigh_mps2), ("shank", prep.acc_offset_shank_mps2)):
        # the session's rests (standing, sitting) fix most of a 1 m/s^2-per-axis offset
        assert np.linalg.norm(true[seg] - off) < 0.6 * np.linalg.norm(true[seg])
    raw = prepare_leg_si("left", si1, si2, 100.0, 100.0,
                         posture=dataclasses.replace(WALKING.posture, rest_offset_max_mps2=0.0))
    assert np.allclose(raw.acc_offset_thigh_mps2, 0.0)
    assert np.allclose(raw.acc_thigh_mps2 - prep.acc_thigh_mps2, prep.acc_offset_thigh_mps2)
    again = prepare_leg_si("left", si1, si2, 100.0, 100.0, shank_shift_s=0.004, reuse=prep)
    assert again.acc_thigh_mps2 is prep.acc_thigh_mps2
    assert np.array_equal(again.acc_offset_thigh_mps2, prep.acc_offset_thigh_mps2)


def test_standing_is_found_whatever_the_accelerometer_offset() -> None:
    """A 0.1 g offset per axis puts |a| at rest ~1.7 m/s^2 off g, beyond the force tolerance: without the rest
    offset the quiet standing of the session would be lost and the level with it."""
    for bias in (0.0, 1.0):
        sim = _session(bias)
        by = {s.segment: s for s in sim.streams}
        synced = synchronised_leg("left", by["thigh"], by["shank"], WALKING)
        leg = build_walking_leg_input(synced.prep, WALKING, axes=synced.axes, fit_gyr=synced.fit_gyr)
        stand = standing_mask(leg)
        assert stand.sum() >= 2 * leg.fs_hz, bias
        t = leg.prep.t_s
        for kind, a, b in sim.info["non_gait_s"]:
            if kind == "sit":  # and sitting is still not standing
                assert not stand[(t > a + 3.0) & (t < b - 3.0)].any(), bias


def test_the_gyro_bias_is_read_at_rest_and_removed() -> None:
    sim = simulate_session(SimConfig(pattern="normal", seed=7, duration_s=80.0, bout_strides=12, legs=("left",),
                                     gyro_bias_dps=4.0))
    by = {s.segment: s for s in sim.streams}
    prep = prepare_leg_si("left", to_si(by["thigh"]), to_si(by["shank"]), 100.0, 100.0)
    for seg, fit in (("thigh", prep.gyr_bias_thigh_rps), ("shank", prep.gyr_bias_shank_rps)):
        true = np.asarray(sim.info["sensors"][f"L-{seg}"]["gyro_bias_dps"])
        assert np.linalg.norm(true) > 2.0
        assert np.linalg.norm(np.degrees(fit) - true) < 0.5  # sway and the slow drift are all that is left
    # the quiet standing before the first bout now reads (almost) no rotation
    first_s = np.degrees(np.median(prep.gyr_thigh_rps[: int(prep.fs_hz)], axis=0))
    assert np.linalg.norm(first_s) < 1.0  # sway


@contextmanager
def _deadline(seconds: int) -> Iterator[None]:
    """Fail instead of hanging (the grouping loop once never ended on a block without a direction)."""
    def fail(*_: object) -> None:
        raise TimeoutError(f"took longer than {seconds} s")
    old = signal.signal(signal.SIGALRM, fail)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_blocks_without_a_direction_are_no_rests() -> None:
    good = np.array([[0.0, 0.0, G_MPS2 + 0.3]] * 5)
    with _deadline(10):
        for bad in ([0.0, 0.0, 0.0], [np.nan, 0.0, 9.8], [0.0, 0.0, 1e-300]):
            fit = fit_rest_offset(np.vstack([good, [bad] * 3]))
            assert np.allclose(fit, [0.0, 0.0, 0.3], atol=0.02), bad
        means, counts = posture_clusters(good, dataclasses.replace(WALKING.posture, rest_orientation_deg=0.0))
        assert counts.sum() == 5  # every block labelled, the loop ends
        assert np.allclose(rest_offsets(np.zeros((500, 3)), np.zeros((500, 3)), np.ones(500, dtype=bool), 100.0),
                           0.0)
        assert np.allclose(fit_rest_offset(good, dataclasses.replace(WALKING.posture, rest_offset_prior_mps2=0.0)), 0.0)


def test_a_session_with_a_silent_accelerometer_is_processed() -> None:
    """A sensor streaming its gyro with the accelerometer off (all zeros) must not stop the session."""
    sim = _session(0.1)
    streams = [dataclasses.replace(s, acc=np.zeros_like(s.acc)) if s.segment == "shank" else s for s in sim.streams]
    assert all(isinstance(s, RawSensorStream) for s in streams)
    with _deadline(60):
        res = process_session(streams, activity="walking")
    leg = res.legs["left"]
    assert leg.diagnostics is not None
    assert leg.diagnostics.acc_offset_shank_mps2 == (0.0, 0.0, 0.0)


def test_the_leg_diagnostics_report_what_was_removed() -> None:
    sim = _session(1.0)
    res = process_session(sim.streams, activity="walking")
    diag = res.legs["left"].diagnostics
    assert diag is not None
    for seg in ("thigh", "shank"):
        true = np.asarray(sim.info["sensors"][f"L-{seg}"]["acc_bias_mps2"])
        reported = np.asarray(getattr(diag, f"acc_offset_{seg}_mps2"))
        assert reported.shape == (3,)
        assert np.linalg.norm(true - reported) < 0.6 * np.linalg.norm(true)
        gyro = np.asarray(getattr(diag, f"gyr_bias_{seg}_dps"))
        assert np.linalg.norm(gyro - np.asarray(sim.info["sensors"][f"L-{seg}"]["gyro_bias_dps"])) < 0.5


def test_a_sensor_far_off_at_rest_is_named_in_a_warning() -> None:
    sim = simulate_session(SimConfig(pattern="normal", seed=7, duration_s=80.0, bout_strides=12, legs=("left",),
                                     acc_bias_ms2=1.5))
    warned = [w for w in process_session(sim.streams, activity="walking").warnings if "off at rest" in w]
    big = {seg for seg in ("thigh", "shank")
           if np.linalg.norm(sim.info["sensors"][f"L-{seg}"]["acc_bias_mps2"]) > 1.5}
    assert big, "the case needs a sensor well beyond the warning threshold"
    assert all(any(f"L-{seg}" in w for w in warned) for seg in big)
    assert not any("off at rest" in w for w in process_session(_session(0.1).streams, activity="walking").warnings)
