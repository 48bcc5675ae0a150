"""pipeline.walking: the joint-centre fit takes gait samples only, so jump landings do not bend the lever arms."""

from __future__ import annotations

import numpy as np

from pipeline import walking
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session


def test_centre_fit_mask_keeps_gait_strides_only() -> None:
    usable = np.ones(1000, dtype=bool)
    usable[150:160] = False  # a gap inside the first stride stays out
    mask = walking.centre_fit_mask(usable, [(100, 160, 210), (210, 270, 320)], min_samples=50)
    assert mask.sum() == 221 - 10 and not mask[:100].any() and not mask[321:].any() and not mask[150:160].any()
    # too few gait samples (or none): every usable sample, as before
    assert walking.centre_fit_mask(usable, [(100, 160, 210)], min_samples=500) is usable
    assert walking.centre_fit_mask(usable, [], min_samples=50) is usable


def _shank_lever_error_m(sim: object, leg: str, o2_m: tuple[float, ...], j2: tuple[float, ...]) -> float:
    """In-plane distance [m] between the fitted and the true shank sensor position (sensor frame)."""
    info = sim.info["sensors"][f"{leg[0].upper()}-shank"]
    rot = np.array(info["mounting"])
    true_o, j = rot.T @ np.array(info["lever_arm_m"]), np.asarray(j2)
    e = np.asarray(o2_m) - true_o
    return float(np.linalg.norm(e - (e @ j) * j))


def test_jump_landings_do_not_enter_the_centre_fit() -> None:
    """Three blocks of vertical jumps between walking bouts (landings shock both shanks like heel strikes, and
    the take-offs are the fastest samples of the session): the shank's lever arm comes from the gait strides and
    stays within a centimetre of the simulator's, the fit's residual near that of walking alone."""
    sim = simulate_session(SimConfig(pattern="normal", seed=4, duration_s=90.0, bout_strides=12,
                                     activities=("jump",)))
    res = process_session(sim.streams)
    for leg, lr in res.legs.items():
        d = lr.diagnostics
        assert _shank_lever_error_m(sim, leg, d.o2_m, d.j2) < 0.01
        assert d.centre_rms_residual_mps2 < 0.2


def _thigh_lever_error_m(sim: object, leg: str, o1_m: tuple[float, ...], j1: tuple[float, ...]) -> float:
    info = sim.info["sensors"][f"{leg[0].upper()}-thigh"]
    rot = np.array(info["mounting"])
    true_o, j = rot.T @ np.array(info["lever_arm_m"]), np.asarray(j1)
    e = np.asarray(o1_m) - true_o
    return float(np.linalg.norm(e - (e @ j) * j))


def test_gait_only_refinement_keeps_the_basin_of_the_whole_session_fit() -> None:
    """Long lever arms (x2): on gait samples alone a multi-start fit settled in a mirrored minimum (the thigh
    sensor placed 60 cm from where it is, +6 deg on the leg's peaks); refined from the whole-session fit it stays
    within a few centimetres."""
    sim = simulate_session(SimConfig(pattern="normal", seed=3, duration_s=90.0, bout_strides=12, lever_scale=2.0))
    res = process_session(sim.streams)
    for leg, lr in res.legs.items():
        d = lr.diagnostics
        assert _thigh_lever_error_m(sim, leg, d.o1_m, d.j1) < 0.06
