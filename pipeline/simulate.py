"""Thigh and shank IMU simulator with exact ground truth (knee angle, gait events, per-stride metrics).

Model
-----
A planar-in-sagittal leg chain embedded in 3-D: the pelvis moves forward along a heading ``psi`` (turns rotate
about the vertical) with a vertical bob; the thigh inclination equals the hip flexion, the shank inclination is
``thigh - knee`` (knee flexion positive). Segment frames (x forward, y left, z up along the segment) are
``R_seg = Rz(psi) @ Ry(-theta)``, so a positive segment angle swings the distal end forward and the knee flexion
rate is ``(omega_shank - omega_thigh) . y`` in segment coordinates.

Joint curves are truncated Fourier series (8 harmonics) of normative gait curves per pattern (Perry and Burnfield,
Gait Analysis, 2nd ed., fig. 7-3/8-3 shapes; Rhudy et al. 2024 fig. 6 for running), heel strike at 0 % of the
cycle, toe-off at the pattern's stance fraction, with smooth stride-to-stride variability. Every scalar degree of
freedom (thigh and shank angles, heading, forward speed, pelvis height) is sampled on a 500 Hz grid and turned into
a quintic interpolating spline; the spline *is* the kinematics. Angular velocity and acceleration are evaluated
from exact spline derivatives by rigid-body kinematics (``a = a_hip + sum alpha x r + omega x (omega x r)``), so
integrating the relative sagittal gyro reproduces the true knee angle to numerical precision.

Sensor effects: arbitrary mounting rotation (random per sensor, mirrored between legs), lever arms from the knee
joint centre, gravity, gyro bias and white noise, accelerometer noise, heel-strike impacts (damped oscillations on
the accelerometers that replace part of the slowing before them, so the sensor's velocity returns
(``impact_balanced``); a small transient rotation on the shank gyro), soft-tissue wobble of the thigh sensor (a
damped transient rotation and translation: it integrates back to zero, as real wobble does), packet loss (dropped
BLE packets and longer outages), per-sensor start offset, timestamp sync error and clock drift.

Robustness options (``SimConfig`` fields after ``acc_unit``; each default reproduces the model above bit for bit,
and each new random effect draws from its own ``default_rng([seed, k])`` stream): the standing and seated knee
angle, per-leg scaled or shifted knee curves, an absolute heel-strike shock in g, larger and off-axis lever arms,
bursty packet loss (Gilbert-Elliott two-state channel per sensor), sharper and more frequent turns, non-gait
movements between bouts (vertical jumps, step-ups onto a stair, a step test of step-ups without rest, stair
flights up and down step over step, sit-to-stand repetitions, seated knee extensions: never strides in the truth;
``walking=False`` makes an exercise session of them alone), a sensor turned on its segment half-way through
(``remount_segment``), wrongly labelled
sensors (legs or thigh/shank swapped), per-axis sensitivity (gain) errors, and 3-D joint motion (``knee_3d``,
``hip_3d``, ``knee_varus_deg``; the thigh sensor's skin turning about the femur with flexion, ``thigh_sta_deg``;
a joint centre that rolls with flexion, ``knee_rollback_mm``):
each segment is then the end of a chain of rotations, pelvis
``Rz(heading + rotation) Rx(obliquity)``, hip and knee each ``Ry(flexion) Rx(ab/adduction) Rz(axial rotation)`` in
the order of the joint coordinate system (Grood and Suntay 1983), whose flexion is the true knee angle.

Pure numpy/scipy, seeded and deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.interpolate import BSpline, CubicSpline, make_interp_spline
from scipy.spatial.transform import Rotation

from pipeline.constants import G_MPS2 as GRAVITY_MS2
from pipeline.types import RawSensorStream

Pattern = Literal["normal", "slow", "fast", "stiff-knee", "crouch", "running"]
PATTERNS: tuple[str, ...] = ("normal", "slow", "fast", "stiff-knee", "crouch", "running")
_GRID_HZ = 500.0
_N_HARMONICS = 8


@dataclass(frozen=True)
class _PatternSpec:
    knee_pts: tuple[tuple[float, float], ...]  # (cycle %, knee flexion deg)
    hip_pts: tuple[tuple[float, float], ...]  # (cycle %, hip flexion deg)
    stride_s: float
    speed_ms: float
    stance_frac: float
    bob_m: float
    impact_g: float


# Keypoints of normative curves; 0 % = heel strike. Shapes after Perry & Burnfield (walking), crouch after
# Rodda & Graham 2004 (CP crouch gait), stiff-knee after Goldberg et al. 2003, running after Novacheck 1998.
# Pre-swing timing checked against the Tan et al. treadmill recordings: the shank angular-velocity minimum
# precedes the force-plate toe-off by 30-50 ms (here 35-55 ms in walking; in running it follows by ~25 ms).
_SPECS: dict[str, _PatternSpec] = {
    "normal": _PatternSpec(
        ((0, 4), (13, 17), (25, 12), (40, 4), (50, 8), (62, 40), (72, 61), (85, 37), (95, 6)),
        ((0, 25), (15, 20), (35, 5), (55, -10), (63, -5), (74, 12), (85, 27), (92, 29)),
        1.10, 1.30, 0.60, 0.025, 2.0),
    "slow": _PatternSpec(
        ((0, 4), (13, 12), (28, 8), (42, 3), (52, 8), (65, 36), (75, 54), (86, 34), (95, 6)),
        ((0, 21), (15, 17), (35, 4), (57, -7), (65, -3), (77, 10), (87, 23), (93, 24)),
        1.40, 0.75, 0.63, 0.015, 1.2),
    "fast": _PatternSpec(
        ((0, 5), (12, 22), (25, 15), (38, 5), (48, 10), (60, 42), (70, 66), (83, 40), (94, 8)),
        ((0, 30), (15, 24), (35, 5), (53, -13), (61, -8), (72, 14), (84, 33), (91, 34)),
        0.95, 1.75, 0.58, 0.035, 3.0),
    "stiff-knee": _PatternSpec(
        ((0, 5), (13, 11), (28, 8), (45, 4), (55, 8), (64, 21), (74, 37), (86, 22), (95, 7)),
        ((0, 26), (15, 21), (35, 5), (57, -8), (64, -5), (75, 13), (86, 29), (92, 30)),
        1.30, 0.90, 0.62, 0.02, 1.5),
    "crouch": _PatternSpec(
        ((0, 30), (12, 37), (28, 31), (44, 25), (52, 28), (63, 44), (73, 57), (85, 45), (95, 33)),
        ((0, 40), (15, 35), (35, 22), (55, 12), (63, 16), (74, 28), (85, 43), (92, 44)),
        1.20, 0.80, 0.62, 0.02, 1.2),
    "running": _PatternSpec(
        ((0, 16), (14, 40), (28, 30), (34, 24), (46, 55), (70, 104), (85, 60), (94, 20)),
        ((0, 35), (20, 20), (37, -10), (46, -5), (65, 25), (80, 45), (90, 42)),
        0.72, 3.0, 0.38, 0.07, 6.0),
}


# Typical 3-D joint motion in walking (cycle %, deg; 0 % = ipsilateral heel strike), scaled by SimConfig.knee_3d
# and hip_3d: hip ab/adduction (+) and internal rotation (+) after Kadaba et al. 1990; the knee's ab/adduction
# (varus +) and the tibia's internal rotation (+) beyond its coupling with flexion after bone-pin studies
# (Lafortune et al. 1992, Benoit et al. 2006: a few deg of ab/adduction, ~9 deg of axial rotation over the cycle,
# internal as the knee flexes: the screw-home mechanism run backwards).
_HIP_ADD_PTS = ((0, 2), (18, 8), (40, 5), (60, -2), (72, -6), (88, -1))
_HIP_INT_PTS = ((0, 4), (15, 6), (45, 1), (62, -5), (78, -3), (92, 3))
_KNEE_ADD_PTS = ((0, 0.5), (15, 2), (45, 1), (62, -1), (75, -2.5), (90, 0))
_KNEE_INT_PTS = ((0, 1), (15, 2), (45, -1), (70, 0), (90, 0.5))


@dataclass(frozen=True)
class _OutOfPlane:
    """Amplitudes of the 3-D motion at ``knee_3d = hip_3d = 1`` (each subject scaled by 0.7-1.3)."""

    knee_rot_per_flex: float = 0.15  # deg of tibial internal rotation per deg of knee flexion above standing
    pelvis_rot_deg: float = 4.0  # pelvic rotation about the vertical (the stepping side forward)
    pelvis_obl_deg: float = 4.0  # pelvic obliquity (the swing side drops)
    pelvis_sway_m: float = 0.025  # lateral sway of the pelvis towards the stance leg
    stand_hip_abd_deg: float = 3.0  # quiet standing with the feet apart
    stand_hip_ext_rot_deg: float = 5.0  # and the toes out


_OUT_OF_PLANE = _OutOfPlane()


@dataclass
class SimConfig:
    """What to simulate. Levels are multipliers (1 = realistic default, 0 = off) unless a unit is named."""

    pattern: str = "normal"
    fs_hz: float = 100.0
    seed: int = 0
    n_strides: int | None = None  # walking strides in total (over all bouts); default 40 unless duration_s
    duration_s: float | None = None  # approximate session length; bouts and breaks are added until reached
    legs: tuple[str, ...] = ("left", "right")
    mounting: Literal["random", "aligned"] = "random"
    bout_strides: int = 20
    activities: tuple[str, ...] = ("standing", "turn", "sitting")  # between bouts, cycled
    walking_turns: bool = True  # a 180 deg turn in the middle of every other bout
    gyro_noise_dps: float = 0.3  # white noise SD per sample
    gyro_bias_dps: float = 1.0  # SD of the constant per-axis bias
    gyro_bias_walk_dps: float = 0.05  # SD of the slow bias drift over a minute
    acc_noise_ms2: float = 0.05
    acc_bias_ms2: float = 0.1
    impact_level: float = 1.0
    wobble_level: float = 1.0
    variability: float = 1.0  # stride-to-stride variability multiplier
    packet_loss: float = 0.002  # probability of dropping one BLE packet
    packet_samples: int = 6
    outages_per_min: float = 0.1  # longer runs of lost samples (0.3-2 s)
    sync_offset_ms: float = 5.0  # SD of each sensor's timestamp error (app-side mapping of the sensor clock)
    clock_drift_ppm: float = 20.0  # SD of each sensor's clock rate error (crystal tolerance)
    shank_fs_hz: float | None = None  # a shank sensor running at another rate than the thigh's (default: same)
    gyro_range_dps: float | None = None  # full-scale range: readings clip there (None: no saturation)
    acc_range_g: float | None = None
    gyro_unit: Literal["deg/s", "rad/s"] = "deg/s"
    acc_unit: Literal["m/s2", "g"] = "m/s2"
    # --- robustness options: each default reproduces the behaviour above exactly ---
    stand_knee_deg: float | None = None  # standing knee flexion of both legs (None: drawn from 2-6 deg)
    stand_knee_right_extra_deg: float = 0.0  # the right knee stands this much more flexed than the left
    sit_knee_deg: float = 90.0  # seated knee flexion (thigh horizontal)
    knee_shift_deg: tuple[float, float] = (0.0, 0.0)  # (left, right) offset added to the gait knee curve
    knee_scale: tuple[float, float] = (1.0, 1.0)  # (left, right) gait knee excursion above its minimum
    # Peak heel-strike shock on the shank accelerometer in g (thigh: 0.3 x). None: impact_level, where 1 gives the
    # pattern's default, a peak of 0.53 x _PatternSpec.impact_g (walking ~1.1 g, running ~3.2 g).
    impact_g: float | None = None
    lever_scale: float = 1.0  # multiplies every sensor's lever arm from the knee joint centre
    lever_offaxis_m: float = 0.0  # extra anterior and lateral offset of every sensor from its segment's axis
    loss_model: Literal["independent", "bursty"] = "independent"  # bursty: Gilbert-Elliott, mean = packet_loss
    loss_burst_packets: float = 4.0  # bursty: mean number of packets per loss burst
    turn_every_bouts: int = 2  # with walking_turns, every n-th bout turns
    turns_per_bout: int = 1
    turn_strides: float = 2.5  # duration of a walking turn in strides (smaller = sharper)
    turn_angle_deg: float = 180.0
    label_swap: Literal["none", "legs", "thighs", "segments", "left_segments"] = "none"  # wrongly labelled sensors
    # quiet standing [s] before the first bout and after the last (None: 2-3 s before, ~3 s after); with one long
    # bout (large bout_strides) and a value below a second, the session contains no quiet standing at all
    standing_s: float | None = None
    # "ringing": the shank shock rings 3 x longer at a lower frequency and rocks the sensor about a random axis
    # (the gyro sees it too), as a loosely strapped sensor would; "default": the model above
    impact_model: Literal["default", "ringing"] = "default"
    # True: every shock and soft-tissue jolt replaces part of the slowing down before it, so the sensor's velocity
    # over a gait cycle returns, as Newton has it (_balanced). False: the damped sine added to the accelerometer alone,
    # which leaves the sensor ~0.07 m/s per g of shock faster along the shank after every strike (no real sensor reads
    # that unless it clips or rectifies)
    impact_balanced: bool = True
    move_reps: int = 3  # repetitions of each jump, step-up or sit-to-stand block between bouts
    # per-axis sensitivity (gain) errors, SD of the relative error (uncalibrated MEMS: 1-3 %); 0: exact gains
    gyro_gain_sd: float = 0.0
    acc_gain_sd: float = 0.0
    jump_rest_s: float = 1.0  # standing between two jumps (0: rhythmic jumping at the jump's own period)
    # 3-D joint motion beyond the sagittal chain (multipliers of typical amplitudes, 0: the planar model above;
    # see _OUT_OF_PLANE). knee_3d: the knee is no hinge (ab/adduction and tibial axial rotation, the rotation
    # coupled to flexion); hip_3d: pelvic rotation, obliquity and lateral sway, hip ab/adduction and rotation.
    # The true knee angle is then the joint coordinate system's flexion (Grood and Suntay 1983).
    knee_3d: float = 0.0
    hip_3d: float = 0.0
    knee_varus_deg: float = 0.0  # static frontal alignment of both knees (varus +, as in medial knee OA)
    # soft-tissue artefact of the thigh sensor: the skin (and strap) turns about the femur's long axis with knee
    # flexion, this many deg at 60 deg of flexion (bone-pin vs skin-marker studies: up to ~10 deg, Benoit et al. 2006)
    thigh_sta_deg: float = 0.0
    # femoral rollback: the knee is no fixed pivot. The shank's origin (the joint centre) moves anteriorly in the
    # thigh's frame by this many mm per 90 deg of flexion above standing (fluoroscopy of healthy knees: the
    # tibiofemoral contact moves back 10-20 mm over the flexion range; Seel's Eq. 5 assumes one fixed centre)
    knee_rollback_mm: float = 0.0
    # walking pace per bout, cycled over the bouts (empty: every bout at the pattern's own pace). A pace p scales the
    # bout's gait excursions (knee, hip, pelvis bob) by p and its cadence by sqrt(p), so the forward speed goes with
    # p^1.5 and the segments' angular velocities with p^1.5 too: 0.5 turns brisk walking into a rehabilitation
    # shuffle (shank swing peaks ~460 -> ~160 deg/s on "fast") in the same session
    bout_pace: tuple[float, ...] = ()
    hip_scale: float = 1.0  # the gait hip curve's excursion about its cycle mean (0.5: a stiff, osteoarthritic hip)
    stair_steps: int = 10  # steps of each flight in a "stair_flight" activity (up, a pause, down)
    # False: an exercise session without walking: each of ``activities`` once, in order, between quiet standing
    walking: bool = True
    # the left leg's sensor of this segment is turned on the limb half-way through the session (a strap re-fastened)
    # by ``remount_deg`` about a random axis of the segment (its own draws) or about the segment's long axis
    remount_segment: Literal["none", "thigh", "shank"] = "none"
    remount_deg: float = 0.0
    remount_axis: Literal["random", "long"] = "random"
    # sensors taken off at the first stop past half-way, one strap after the other (thigh first), and left lying on a
    # table (housing face down or up, any heading) while the person walks on: the left leg's two sensors or all four
    # (the truth keeps the person's knees)
    off_body: Literal["none", "left", "all"] = "none"


@dataclass(frozen=True)
class TruthStride:
    """One true stride (heel strike to the next heel strike); metrics as in :class:`pipeline.types.StrideMetrics`."""

    leg: str
    t_start_s: float
    t_end_s: float
    t_toe_off_s: float
    peak_swing_flexion_deg: float
    min_flexion_deg: float
    rom_deg: float
    stance_flexion_deg: float
    steady: bool  # full gait amplitude over the whole stride (not gait initiation / termination)
    turning: bool


@dataclass
class LegTruth:
    """Ground truth of one leg: the knee angle on a 500 Hz grid, gait events, strides and walking bouts."""

    leg: str
    t_s: np.ndarray  # true time (session clock), uniform at 500 Hz
    angle_deg: np.ndarray  # knee flexion
    heel_strikes_s: np.ndarray
    toe_offs_s: np.ndarray
    strides: list[TruthStride]
    bouts_s: list[tuple[float, float]]  # walking bouts (first to last heel strike)
    stand_knee_deg: float = float("nan")  # quiet-standing knee flexion of this leg (before sway)

    def angle_at(self, t_s: np.ndarray) -> np.ndarray:
        return np.interp(t_s, self.t_s, self.angle_deg)


@dataclass
class SimSession:
    """One simulated session: the raw streams as a phone would upload them and the truth per leg."""

    config: SimConfig
    activity: str
    duration_s: float
    streams: list[RawSensorStream]
    truth: dict[str, LegTruth]
    info: dict = field(default_factory=dict)  # mounting matrices, lever arms, biases, clock errors per sensor


# ---------------------------------------------------------------------------------------------------------------
# Normative curves


def _fourier_coefs(points: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Complex Fourier coefficients (0.._N_HARMONICS) of the periodic cubic spline through the keypoints."""
    x = np.array([p[0] for p in points] + [100.0]) / 100.0
    y = np.array([p[1] for p in points] + [points[0][1]])
    phase = np.arange(1024) / 1024
    dense = CubicSpline(x, y, bc_type="periodic")(phase)
    return np.fft.rfft(dense)[: _N_HARMONICS + 1] / 1024


def _eval_fourier(coefs: np.ndarray, phase: np.ndarray) -> np.ndarray:
    k = np.arange(len(coefs))
    z = np.exp(2j * np.pi * np.outer(phase, k))
    w = np.where(k == 0, 1.0, 2.0)
    return (z * (coefs * w)).real.sum(axis=1)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2)


# ---------------------------------------------------------------------------------------------------------------
# Timeline


@dataclass
class _Bout:
    t0: float
    t1: float
    turn: bool


@dataclass
class _Moves:
    """Non-gait movements between bouts: knee/hip offsets per leg (deg) and pelvis height offset (m) on the grid,
    landing times (a shock like a heel strike), and every non-gait interval (kind, start, end) incl. sitting."""

    knee: dict[str, np.ndarray] = field(default_factory=dict)
    hip: dict[str, np.ndarray] = field(default_factory=dict)
    height: np.ndarray | None = None
    landings_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    non_gait_s: list[tuple[str, float, float]] = field(default_factory=list)


@dataclass
class _Timeline:
    t: np.ndarray
    env: np.ndarray  # gait amplitude 0..1
    phase: np.ndarray  # left-leg gait phase (cycles)
    sit: np.ndarray  # 0 standing .. 1 sitting
    heading_rad: np.ndarray
    bouts: list[_Bout]
    moves: _Moves = field(default_factory=_Moves)
    pace: np.ndarray | float = 1.0  # SimConfig.bout_pace on the grid (1 between bouts, where env is 0)


# Keyframes of non-gait movements: (time s, knee deg, hip deg, pelvis height m) relative to quiet standing.
# Countermovement vertical jump: squat (shank tilted ~30 deg forward: knee = hip + ankle dorsiflexion), push-off,
# ~0.25 m flight, landing with flexion, recovery.
_JUMP = np.array([(0.0, 0, 0, 0.0), (0.6, 85, 55, -0.25), (0.9, -2, 0, 0.08), (1.15, 12, 8, 0.32),
                  (1.4, 0, 0, 0.06), (1.6, 60, 40, -0.15), (2.4, 0, 0, 0.0)])
_JUMP_LANDING_S = 1.4
# Step up onto a 17 cm stair and back down (lead leg up, trail up, lead down, trail down): columns
# (time s, lead knee, lead hip, trail knee, trail hip, pelvis height m).
_STEP = np.array([(0.0, 0, 0, 0, 0, 0.0), (0.5, 90, 65, 0, 0, 0.0), (0.8, 65, 50, 5, -5, 0.0),
                  (1.5, 5, 5, 60, 30, 0.17), (2.0, 0, 0, 0, 0, 0.17), (2.6, 25, -5, 45, 30, 0.05),
                  (3.0, 5, 0, 50, 35, -0.02), (3.4, 5, 0, 40, 25, 0.0), (3.9, 0, 0, 0, 0, 0.0)])
_MOVE_REPS = 3
# Step-over-step stair gait, 0 % = foot contact on the next step (cycle %, deg): knee and hip flexion of stair
# ascent and descent after Riener et al. 2002 and Protopapadaki et al. 2007 (ascent: contact at ~60 deg of knee
# flexion, extension under load to ~10 deg, swing peak ~90 deg; descent: contact at ~10 deg, flexion under load to
# ~75 deg before toe-off, swing peak ~95 deg), with their stride times (two steps) and a 17 cm step.
_STAIR_UP = (((0, 62), (10, 58), (25, 35), (40, 15), (55, 10), (63, 18), (72, 60), (82, 92), (92, 84)),
             ((0, 60), (20, 45), (40, 20), (55, 8), (65, 15), (80, 55), (90, 65)), 1.40)
_STAIR_DOWN = (((0, 8), (10, 18), (25, 25), (40, 40), (55, 75), (65, 92), (75, 97), (87, 55), (95, 15)),
               ((0, 22), (15, 18), (35, 12), (55, 20), (70, 35), (85, 38), (95, 28)), 1.30)
_STAIR_RISE_M = 0.17
_STAIR_TOP_S = 1.5  # standing on the landing between the flight up and the flight down
# Marching in place (a rehabilitation warm-up, "high knees" at a walking cadence): each leg in turn lifted and
# lowered, hip to 55 deg and knee to 75 deg, 0.7 s a leg; columns as _STEP. The foot leaves and meets the floor
# beside the other one: the leg swings without stepping anywhere.
_MARCH = np.array([(0.0, 0, 0, 0, 0, 0.0), (0.35, 75, 55, 0, 0, 0.0), (0.7, 0, 0, 0, 0, 0.0),
                   (1.05, 0, 0, 75, 55, 0.0), (1.4, 0, 0, 0, 0, 0.0)])
# High knees (a brisk variant): the hip lifted to 75 deg, higher than the knee bends (70), 0.44 s a leg.
_HIGH_KNEES = np.array([(0.0, 0, 0, 0, 0, 0.0), (0.22, 70, 75, 0, 0, 0.0), (0.44, 0, 0, 0, 0, 0.0),
                        (0.66, 0, 0, 70, 75, 0.0), (0.88, 0, 0, 0, 0, 0.0)])
_MARCHES = {"march": _MARCH, "high_knees": _HIGH_KNEES}
_STEP_TEST_REP_S = 2.4  # a step test's up-up-down-down at 100 steps/min (the step-up keyframes, compressed)
# Seated knee extension (long-arc quadriceps exercise): (time s, knee extension from the seated angle as a share of
# the way to _EXTENSION_KNEE_DEG): lift over 1.5 s, hold 2 s, lower over 1.5 s, rest 1.5 s.
_EXTENSION = np.array([(0.0, 0.0), (1.5, 1.0), (3.5, 1.0), (5.0, 0.0), (6.5, 0.0)])
_SIT_RAMP_S = 2.0  # sitting down and standing up, unless the activity says otherwise
_EXTENSION_KNEE_DEG = 10.0  # the knee's angle at the top of the lift (a knee after surgery rarely straightens fully)
_IMPACT_FREQ_HZ, _IMPACT_TAU_S = 28.0, 0.012  # heel-strike shock: damped sine on the accelerometers
# With an absolute impact_g, the shank sensor's transient rotation grows with the shock up to running's default.
_IMPACT_ROT_MAX_DEG = 3.0
_SHOCK_LEAD_S = 0.015  # the time constant of the slowing before a shock that the shock replaces (impact_balanced)
_OFF_BODY_MOVE_S = 2.0  # taking a sensor off its strap and laying it on a table
_OFF_BODY_NEXT_S = 1.0  # between laying one sensor down and taking the next one off


def _damped_sine_peak(freq_hz: float, tau_s: float) -> float:
    """Peak of exp(-u/tau) sin(2 pi f u) over u >= 0 (at tan(w u) = w tau)."""
    w = 2 * np.pi * freq_hz
    u = np.arctan(w * tau_s) / w
    return float(np.exp(-u / tau_s) * np.sin(w * u))


def _balanced(pulse: np.ndarray, t: np.ndarray, onsets: np.ndarray, r_sensor: np.ndarray, d_sensor: np.ndarray
              ) -> np.ndarray:
    """Specific force (N, 3) in the sensor frame of a shock train ``pulse`` (N,) [m/s^2] along ``d_sensor`` as it
    points at each onset, held fixed in the world (``r_sensor`` (N, 3, 3): sensor to world), with the shock's velocity
    change taken away over the ``_SHOCK_LEAD_S`` before it (a lobe ``u exp(u/tau)``). The smooth gait kinematics slow
    the shank down before heel contact; in truth much of that happens at contact, in the shock, so the shock's velocity
    change replaces part of theirs and the sensor's velocity over a gait cycle returns (Newton)."""
    out = np.zeros((t.size, 3))
    if len(onsets) == 0:
        return out
    dt = np.diff(t, append=t[-1])
    starts = np.searchsorted(t, onsets)
    stops = np.searchsorted(t, np.append(onsets[1:], np.inf))
    for i0, i1, t0 in zip(starts, stops, onsets, strict=True):
        if i1 <= i0:
            continue
        dv = float(np.sum(pulse[i0:i1] * dt[i0:i1]))
        j0 = int(np.searchsorted(t, t0 - 8 * _SHOCK_LEAD_S))
        lobe = -(t[j0:i0] - t0) * np.exp((t[j0:i0] - t0) / _SHOCK_LEAD_S)
        area = float(np.sum(lobe * dt[j0:i0]))
        d_w = r_sensor[i0] @ d_sensor
        if area > 0:
            out[j0:i0] -= (dv / area) * lobe[:, None] * np.einsum("nji,j->ni", r_sensor[j0:i0], d_w)
        out[i0:i1] += pulse[i0:i1, None] * np.einsum("nji,j->ni", r_sensor[i0:i1], d_w)
    return out


def _keyframes(grid: np.ndarray, t0: float, frames: np.ndarray) -> np.ndarray:
    """Columns 1.. of ``frames`` interpolated by quintic smoothsteps between keyframes (C2, rest at each one);
    zero outside the movement."""
    out = np.zeros((len(grid), frames.shape[1] - 1))
    ts = t0 + frames[:, 0]
    for i in range(len(frames) - 1):
        seg = (grid >= ts[i]) & (grid < ts[i + 1])
        u = _smoothstep((grid[seg] - ts[i]) / (ts[i + 1] - ts[i]))
        out[seg] = frames[i, 1:] + (frames[i + 1, 1:] - frames[i, 1:]) * u[:, None]
    return out


# between-bout movements made by _add_moves
_MOVES = ("jump", "stairs", "stair_flight", "step_test", "march", "high_knees")


def _move_duration_s(kind: str, reps: int = _MOVE_REPS, jump_rest_s: float = 1.0) -> float:
    if kind == "jump":
        return reps * (_JUMP[-1, 0] + jump_rest_s)
    if kind == "stairs":
        return reps * (_STEP[-1, 0] + 0.8)
    if kind == "stair_flight":
        return 0.5 * reps * (_STAIR_UP[2] + _STAIR_DOWN[2]) + _STAIR_TOP_S + 0.5 * (_STAIR_UP[2] + _STAIR_DOWN[2])
    if kind == "step_test":
        return reps * _STEP_TEST_REP_S
    if kind in _MARCHES:
        return reps * _MARCHES[kind][-1, 0]
    if kind == "seated_extension":
        return reps * _EXTENSION[-1, 0]
    return reps * (1.5 + 2.5 + 1.5 + 2.0)  # sit_to_stand: down, seated, up, standing


def _break_reps(cfg: SimConfig, kind: str) -> int:
    """Repetitions of a break's movement: steps of a stair flight, else ``move_reps``."""
    return cfg.stair_steps if kind == "stair_flight" else cfg.move_reps


def _break_duration(cfg: SimConfig, kind: str, rng: np.random.Generator) -> tuple[float, float]:
    """A break's duration [s] with activity ``kind``, and how long it sits [s] if it is ``sitting``."""
    sit_s = rng.uniform(8, 15)
    brk = {"sitting": 5.5 + sit_s, "turn": 5.0}.get(kind, rng.uniform(4, 8))
    reps = _break_reps(cfg, kind)
    if kind in _MOVES or kind == "sit_to_stand":
        brk = _move_duration_s(kind, reps, cfg.jump_rest_s) + 3.0
    if kind == "seated_extension":
        brk = 1.0 + _seated_block_s(reps) + 1.0
    return brk, sit_s


def _seated_block_s(reps: int) -> float:
    """Sitting down, settling 1 s, ``reps`` seated knee extensions, 1 s, standing up [s]."""
    return _SIT_RAMP_S + 1.0 + _move_duration_s("seated_extension", reps) + 1.0 + _SIT_RAMP_S


def _break_events(cfg: SimConfig, kind: str, t: float, k: int, sit_s: float, rng: np.random.Generator
                  ) -> list[tuple[str, float, float, dict]]:
    """The events (kind, t0, t1, params) of the ``k``-th break, activity ``kind``, from ``t`` (_break_duration)."""
    reps = _break_reps(cfg, kind)
    if kind == "sitting":
        return [("sit", t + 1.0, t + 1.0 + 2.0 + sit_s + 2.0, {})]
    if kind == "turn":
        return [("turn", t + 1.0, t + 3.5, {"angle": np.pi * rng.choice([-1, 1]) * rng.uniform(0.5, 1)})]
    if kind == "sit_to_stand":
        rep_s = _move_duration_s(kind, cfg.move_reps) / cfg.move_reps
        return [("sit", t_r, t_r + 1.5 + 2.5 + 1.5, {"ramp": 1.5})
                for t_r in t + 1.0 + rep_s * np.arange(cfg.move_reps)]
    if kind == "seated_extension":  # seated, then each knee in turn extends and lowers, the thigh on the chair
        t_ext = t + 1.0 + _SIT_RAMP_S + 1.0
        return [("sit", t + 1.0, t + 1.0 + _seated_block_s(reps), {}),
                (kind, t_ext, t_ext + _move_duration_s(kind, reps),
                 {"lead": k % 2, "reps": reps, "extend_deg": cfg.sit_knee_deg - _EXTENSION_KNEE_DEG})]
    if kind in _MOVES:
        return [(kind, t + 1.0, t + 1.0 + _move_duration_s(kind, reps, cfg.jump_rest_s),
                 {"lead": k % 2, "reps": reps})]
    return []


def _build_timeline(cfg: SimConfig, spec: _PatternSpec, rng: np.random.Generator) -> _Timeline:  # noqa: C901 - one pass over the bout/break plan keeps the random draws in a fixed order (seeded outputs stay reproducible)
    """Lay out bouts and breaks; return the smooth global envelopes on the 500 Hz grid."""
    stride_s = spec.stride_s * float(np.clip(1 + 0.05 * rng.standard_normal(), 0.9, 1.1))
    total_strides = cfg.n_strides if cfg.n_strides is not None else (None if cfg.duration_s else 40)
    events: list[tuple[str, float, float, dict]] = []  # (kind, t0, t1, params)
    t = 2.0 + rng.uniform(0, 1)  # quiet standing first: apps start recording before the patient walks
    tail_s = 3.0
    if cfg.standing_s is not None:
        t = tail_s = cfg.standing_s
    done = 0
    k = 0
    if not cfg.walking:
        for k, kind in enumerate(cfg.activities):
            brk, sit_s = _break_duration(cfg, kind, rng)
            events += _break_events(cfg, kind, t, k, sit_s, rng)
            t += brk
    while cfg.walking:
        pace = cfg.bout_pace[k % len(cfg.bout_pace)] if cfg.bout_pace else 1.0
        bout_stride_s = stride_s / np.sqrt(pace)
        if total_strides is not None:
            n = min(cfg.bout_strides, total_strides - done)
        else:
            n = int(min(cfg.bout_strides, max(3, ((cfg.duration_s or 0) - t - tail_s) / bout_stride_s)))
        if n < 3:
            break
        dur = n * bout_stride_s
        turn = cfg.walking_turns and k % cfg.turn_every_bouts == cfg.turn_every_bouts - 1 and n >= 8
        events.append(("walk", t, t + dur, {"turn": turn, "pace": pace, "stride_s": bout_stride_s}))
        t += dur
        done += n
        if total_strides is not None and done >= total_strides:
            break
        if cfg.duration_s is not None and t > cfg.duration_s - 6:
            break
        kind = cfg.activities[k % len(cfg.activities)] if cfg.activities else "standing"
        brk, sit_s = _break_duration(cfg, kind, rng)
        if cfg.duration_s is not None and t + brk + 3 * stride_s + 3 > cfg.duration_s:
            break
        events += _break_events(cfg, kind, t, k, sit_s, rng)
        t += brk
        k += 1
    t_end = max(t + 2.5, cfg.duration_s or 0.0) if cfg.standing_s is None else t + cfg.standing_s
    grid = np.arange(0.0, t_end + 1e-9, 1.0 / _GRID_HZ)
    env = np.zeros_like(grid)
    sit = np.zeros_like(grid)
    heading = np.zeros_like(grid)
    freq = np.zeros_like(grid)
    pace_grid = np.ones_like(grid) if cfg.bout_pace else 1.0
    bouts: list[_Bout] = []
    moves = _Moves()
    for kind, t0, t1, p in events:
        if kind == "walk":
            bout_stride_s = p["stride_s"]
            # Gait initiation/termination: amplitude ramps over the first and last stride.
            ramp = np.minimum(_smoothstep((grid - t0) / bout_stride_s), _smoothstep((t1 - grid) / bout_stride_s))
            env = np.maximum(env, ramp)
            inside = (grid >= t0) & (grid <= t1)
            n = max(1, round((t1 - t0) / bout_stride_s))
            cv = 0.02 * cfg.variability
            per = 1.0 / (bout_stride_s * np.clip(1 + cv * rng.standard_normal(n + 2), 0.85, 1.15))
            knots = t0 + (np.arange(n + 2) - 0.5) * bout_stride_s
            freq[inside] = CubicSpline(knots, per)(grid[inside])
            if cfg.bout_pace:
                pace_grid[inside] = p["pace"]
            bouts.append(_Bout(t0, t1, bool(p["turn"])))
            if p["turn"]:
                n_turns = max(1, cfg.turns_per_bout)
                mids = [0.5 * (t0 + t1)] if n_turns == 1 else \
                    [t0 + (i + 1) / (n_turns + 1) * (t1 - t0) for i in range(n_turns)]
                ts = cfg.turn_strides
                for i, mid in enumerate(mids):
                    sign = 1.0 if i % 2 == 0 else -1.0  # several turns per bout: alternate, like a slalom
                    heading += sign * np.pi * (cfg.turn_angle_deg / 180.0) * _smoothstep(
                        (grid - mid + 0.5 * ts * bout_stride_s) / (ts * bout_stride_s))
        elif kind == "sit":
            ramp = p.get("ramp", _SIT_RAMP_S)
            down = _smoothstep((grid - t0) / ramp)
            up = _smoothstep((grid - (t1 - ramp)) / ramp)
            sit += down - up
            moves.non_gait_s.append(("sit", t0, t1))
        elif kind in _MOVES:
            _add_moves(moves, grid, kind, t0, p["lead"], cfg.legs, p["reps"], cfg.jump_rest_s)
        elif kind == "seated_extension":
            _add_seated_extensions(moves, grid, t0, p["lead"], cfg.legs, p["reps"], p["extend_deg"])
        elif kind == "turn":
            heading += p["angle"] * _smoothstep((grid - t0) / (t1 - t0))
    phase = np.concatenate([[0.0], np.cumsum(0.5 * (freq[1:] + freq[:-1]) / _GRID_HZ)])
    # Each bout starts with a left heel strike: shift the phase to an integer at the bout start.
    for b in bouts:
        i0 = int(np.searchsorted(grid, b.t0))
        i1 = int(np.searchsorted(grid, b.t1, side="right"))
        frac = phase[i0] - np.floor(phase[i0])
        phase[i0:] += (1 - frac) % 1
        del i1
    return _Timeline(grid, env, phase, sit, heading, bouts, moves, pace_grid)


def _add_moves(mv: _Moves, grid: np.ndarray, kind: str, t0: float, lead: int, legs: tuple[str, ...],
               reps: int = _MOVE_REPS, jump_rest_s: float = 1.0) -> None:
    """Add ``reps`` jumps, step-ups or marching steps (each leg once) starting at t0 to the movement layers ``mv``."""
    _start_layers(mv, grid, legs)
    if kind == "stair_flight":
        _add_stair_flight(mv, grid, t0, lead, legs, reps)
        return
    rep_s = _move_duration_s(kind, reps, jump_rest_s) / reps
    frames = _MARCHES.get(kind, _STEP)
    if kind == "step_test":  # no rest between repetitions: the keyframes' own rests only
        frames = _STEP * np.array([_STEP_TEST_REP_S / _STEP[-1, 0], 1, 1, 1, 1, 1])
    for r in range(reps):
        t_r = t0 + r * rep_s
        if kind == "jump":
            kf = _keyframes(grid, t_r, _JUMP)
            for leg in legs:
                mv.knee[leg] += kf[:, 0]
                mv.hip[leg] += kf[:, 1]
            mv.height += kf[:, 2]
            mv.landings_s = np.append(mv.landings_s, t_r + _JUMP_LANDING_S)
        else:
            kf = _keyframes(grid, t_r, frames)
            # step-ups alternate the lead leg; a march's repetition already takes both legs in turn
            lead_leg = ("left", "right")[(lead + (0 if kind in _MARCHES else r)) % 2]
            if kind in _MARCHES:  # each foot meets the floor as its lowering ends
                mv.landings_s = np.append(mv.landings_s, t_r + frames[[2, 4], 0])
            for leg in legs:
                c = 0 if leg == lead_leg else 2
                mv.knee[leg] += kf[:, c]
                mv.hip[leg] += kf[:, c + 1]
            mv.height += kf[:, 4]
    mv.non_gait_s.append((kind, t0, t0 + _move_duration_s(kind, reps, jump_rest_s)))


def _add_seated_extensions(mv: _Moves, grid: np.ndarray, t0: float, lead: int, legs: tuple[str, ...], reps: int,
                           extend_deg: float) -> None:
    """``reps`` seated knee extensions from t0, the legs in turn (the lead leg first), each ``extend_deg`` up from
    the seated knee angle; the thigh stays on the chair."""
    _start_layers(mv, grid, legs)
    rep_s = _EXTENSION[-1, 0]
    for r in range(reps):
        leg = ("left", "right")[(lead + r) % 2]
        if leg in legs:
            mv.knee[leg] -= extend_deg * _keyframes(grid, t0 + r * rep_s, _EXTENSION)[:, 0]
    mv.non_gait_s.append(("seated_extension", t0, t0 + reps * rep_s))


def _start_layers(mv: _Moves, grid: np.ndarray, legs: tuple[str, ...]) -> None:
    """Zero movement layers on ``grid`` for every leg, unless ``mv`` has them already."""
    if mv.height is None:
        mv.height = np.zeros_like(grid)
        for leg in legs:
            mv.knee[leg] = np.zeros_like(grid)
            mv.hip[leg] = np.zeros_like(grid)


def _add_stair_flight(mv: _Moves, grid: np.ndarray, t0: float, lead: int, legs: tuple[str, ...], steps: int
                      ) -> None:
    """A flight of ``steps`` stairs up, a pause on the landing, and the same flight down (step over step, the legs
    in anti-phase), from t0; the foot contacts shock like heel strikes."""
    t = t0
    for (knee_pts, hip_pts, stride_s), sign in ((_STAIR_UP, 1.0), (_STAIR_DOWN, -1.0)):
        dur = 0.5 * (steps + 1) * stride_s  # one extra step: the envelope's ramps
        env = np.minimum(_smoothstep((grid - t) / (0.5 * stride_s)), _smoothstep((t + dur - grid) / (0.5 * stride_s)))
        env[(grid < t) | (grid > t + dur)] = 0.0
        knee_c, hip_c = _fourier_coefs(knee_pts), _fourier_coefs(hip_pts)
        for leg in legs:
            first = leg == ("left", "right")[lead % 2]
            phase = ((grid - t) / stride_s + (0.0 if first else 0.5)) % 1.0
            mv.knee[leg] += env * _eval_fourier(knee_c, phase)
            mv.hip[leg] += env * _eval_fourier(hip_c, phase)
            n_contacts = int(dur / stride_s) + 1
            contacts = t + (np.arange(n_contacts) + (0.0 if first else 0.5)) * stride_s
            mv.landings_s = np.append(mv.landings_s, contacts[(contacts > t + 0.5 * stride_s)
                                                              & (contacts < t + dur - 0.5 * stride_s)])
        rise = np.cumsum(env)
        rise = steps * _STAIR_RISE_M * rise / max(rise[-1], 1e-9)
        mv.height += sign * rise
        mv.non_gait_s.append(("stairs_up" if sign > 0 else "stairs_down", t, t + dur))
        t += dur + (_STAIR_TOP_S if sign > 0 else 0.0)
    mv.landings_s = np.sort(mv.landings_s)


def _remounted(cfg: SimConfig, r_mount: np.ndarray, t_s: np.ndarray, at_s: float, gyr: np.ndarray, acc: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Readings (N, 3) of a sensor turned on its segment at ``at_s`` (true time) by ``cfg.remount_deg``: the mounting
    becomes ``R_seg r_mount``, so each later reading is ``r_mount^T R_seg^T r_mount`` times the one it would have
    been; and the turn for the session's info (time, new mounting)."""
    if cfg.remount_axis == "long":
        axis = np.array([0.0, 0.0, 1.0])
    else:
        axis = np.random.default_rng([cfg.seed, 6]).standard_normal(3)
        axis /= np.linalg.norm(axis)
    r_seg = _axis_angle(axis, np.array([np.radians(cfg.remount_deg)]))[0]
    m = r_mount.T @ r_seg.T @ r_mount
    later = t_s > at_s
    gyr, acc = gyr.copy(), acc.copy()
    gyr[later] = gyr[later] @ m.T
    acc[later] = acc[later] @ m.T
    return gyr, acc, {"at_s": at_s, "mounting": (r_seg @ r_mount).tolist()}


def _off_body_at(truth: dict[str, LegTruth], t_end: float) -> float:
    """When the sensors come off [s]: half a second after the first walking bout that ends past half-way has ended on
    every leg (a person stops to take them off), else half-way."""
    ends = [min(ends) for lt in truth.values() if (ends := [b1 for _, b1 in lt.bouts_s if b1 > t_end / 2])]
    return max(ends) + 0.5 if ends else t_end / 2


def _taken_off(cfg: SimConfig, leg: str, seg: str, r_sensor: np.ndarray, skin_normal: np.ndarray, t_s: np.ndarray,
               at_s: float, gyr: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Readings (N, 3) of a sensor taken off its segment at ``at_s`` (true time) and laid on a table: turned over
    ``_OFF_BODY_MOVE_S`` about one sensor-fixed axis (a smooth geodesic, so the gyro integrates to the new
    orientation) into lying flat on its housing, the face that was on the skin (``skin_normal``, sensor frame,
    pointing out of the skin) up or down, any heading (its own draws); then still, gravity only. The heel-strike
    transients stop with it. ``r_sensor`` (N, 3, 3): sensor-to-world on the body."""
    rng = np.random.default_rng([cfg.seed, 7, 0 if leg == "left" else 1, 0 if seg == "thigh" else 1])
    up = np.array([0.0, 0.0, 1.0 if rng.random() < 0.5 else -1.0])
    flat = Rotation.align_vectors(up[None, :], skin_normal[None, :])[0].as_matrix()
    r_table = _rz(np.array([rng.uniform(0, 2 * np.pi)]))[0] @ flat
    i0 = int(np.searchsorted(t_s, at_s))
    if i0 >= len(t_s):
        return gyr, acc, {}
    r0 = r_sensor[i0]
    rel = Rotation.from_matrix(r0.T @ r_table).as_rotvec()
    theta = float(np.linalg.norm(rel))
    u = rel / theta if theta > 0 else np.array([1.0, 0.0, 0.0])
    s = np.clip((t_s[i0:] - at_s) / _OFF_BODY_MOVE_S, 0.0, 1.0)
    rot = r0 @ _axis_angle(u, theta * _smoothstep(s))
    gyr, acc = gyr.copy(), acc.copy()
    rate = theta * 30.0 * s**2 * (1.0 - s) ** 2 / _OFF_BODY_MOVE_S  # d/dt of _smoothstep
    gyr[i0:] = rate[:, None] * u
    acc[i0:] = np.einsum("nji,j->ni", rot, np.array([0.0, 0.0, GRAVITY_MS2]))
    return gyr, acc, {"at_s": at_s, "table": r_table.tolist()}


def _smooth_noise(rng: np.random.Generator, t: np.ndarray, sd: float, corr_s: float) -> np.ndarray:
    """Smooth random signal: a cubic spline through N(0, sd) knots every ``corr_s`` seconds (C2, so its
    derivatives stay small and realistic)."""
    if sd == 0 or len(t) == 0:
        return np.zeros(len(t))
    knots = np.arange(t[0] - corr_s, t[-1] + 2 * corr_s, corr_s)
    return CubicSpline(knots, sd * rng.standard_normal(len(knots)))(t)


def _per_stride_signal(rng: np.random.Generator, phase: np.ndarray, sd: float) -> np.ndarray:
    """A smooth signal taking one random value per stride (cubic through the stride mid-points)."""
    n = int(np.ceil(phase[-1])) + 3
    vals = sd * rng.standard_normal(n)
    return CubicSpline(np.arange(n) - 0.5, vals)(phase)


# ---------------------------------------------------------------------------------------------------------------
# Rigid-body kinematics


def _rz(psi: np.ndarray) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    o, z = np.ones_like(psi), np.zeros_like(psi)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _seg_rot(psi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Segment-to-world rotation Rz(psi) @ Ry(-theta)."""
    c, s = np.cos(-theta), np.sin(-theta)
    o, z = np.ones_like(theta), np.zeros_like(theta)
    ry = np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)
    return _rz(psi) @ ry


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (N,3,3) about one unit axis by angles (N,) (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


@dataclass
class _LegSplines:
    thigh: BSpline
    shank: BSpline
    # 3-D joint motion (SimConfig.knee_3d / hip_3d / knee_varus_deg): each segment's rotations after the heading,
    # (axis, angle spline [rad]) with axis 0/1/2 = x/y/z of the frame rotated so far (:func:`_chain_motion`)
    thigh_links: tuple[tuple[int, BSpline], ...] | None = None
    shank_links: tuple[tuple[int, BSpline], ...] | None = None
    # the thigh sensor's own chain: the femur's plus the skin's turn about the femur's long axis (thigh_sta_deg)
    thigh_sensor_links: tuple[tuple[int, BSpline], ...] | None = None


@dataclass
class _BodySplines:
    heading: BSpline
    speed: BSpline
    height: BSpline
    # 3-D pelvis (SimConfig.hip_3d): its rotations after the heading and its lateral sway [m] (None: planar)
    pelvis_links: tuple[tuple[int, BSpline], ...] | None = None
    sway: BSpline | None = None


def _eval3(sp: BSpline, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return sp(t), sp(t, 1), sp(t, 2)


def _segment_motion(body: _BodySplines, theta: BSpline, t: np.ndarray):
    """Rotation, world angular velocity and world angular acceleration of a segment at times t."""
    psi, dpsi, ddpsi = _eval3(body.heading, t)
    th, dth, ddth = _eval3(theta, t)
    rot = _seg_rot(psi, th)
    zero = np.zeros_like(t)
    y_h = np.stack([-np.sin(psi), np.cos(psi), zero], -1)
    x_h = np.stack([np.cos(psi), np.sin(psi), zero], -1)
    z_w = np.stack([zero, zero, np.ones_like(t)], -1)
    omega = dpsi[:, None] * z_w - dth[:, None] * y_h
    # d/dt(y_h) = -dpsi * x_h
    alpha = ddpsi[:, None] * z_w - ddth[:, None] * y_h + (dth * dpsi)[:, None] * x_h
    return rot, omega, alpha


def _hip_acc(body: _BodySplines, t: np.ndarray, side: float, half_width_m: float) -> np.ndarray:
    psi, dpsi, ddpsi = _eval3(body.heading, t)
    v, dv = body.speed(t), body.speed(t, 1)
    ddz = body.height(t, 2)
    zero = np.zeros_like(t)
    x_h = np.stack([np.cos(psi), np.sin(psi), zero], -1)
    y_h = np.stack([-np.sin(psi), np.cos(psi), zero], -1)
    acc = dv[:, None] * x_h + (v * dpsi)[:, None] * y_h
    acc[:, 2] += ddz
    acc += side * half_width_m * (-ddpsi[:, None] * x_h - (dpsi**2)[:, None] * y_h)
    return acc


def _elementary(axis: int, q: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) about the frame's own x (0), y (1) or z (2) axis by angles ``q`` (N,) [rad]."""
    c, s = np.cos(q), np.sin(q)
    out = np.zeros((q.shape[0], 3, 3))
    i, j = [k for k in range(3) if k != axis]
    out[:, axis, axis] = 1.0
    sign = 1.0 if axis != 1 else -1.0  # Ry's sine sits on the other side (right-handed)
    out[:, i, i], out[:, j, j] = c, c
    out[:, i, j], out[:, j, i] = -sign * s, sign * s
    return out


def _chain_motion(body: _BodySplines, links: tuple[tuple[int, BSpline], ...], t: np.ndarray):
    """Rotation, world angular velocity and world angular acceleration of ``Rz(heading) @ R_a0(q0) @ R_a1(q1) ...``
    at times ``t``: each elementary rotation adds its rate about its axis as the frame so far carries it,
    ``omega_i = omega_{i-1} + a_i dq_i``, ``alpha_i = alpha_{i-1} + a_i ddq_i + omega_{i-1} x a_i dq_i``
    (``a_i``: the axis in world coordinates), so both are exact derivatives of the splines."""
    psi, dpsi, ddpsi = _eval3(body.heading, t)
    rot = _rz(psi)
    z_w = np.zeros((t.shape[0], 3))
    z_w[:, 2] = 1.0
    omega = dpsi[:, None] * z_w
    alpha = ddpsi[:, None] * z_w
    for axis, sp in links:
        q, dq, ddq = _eval3(sp, t)
        a_w = rot[:, :, axis]
        alpha = alpha + a_w * ddq[:, None] + np.cross(omega, a_w) * dq[:, None]
        omega = omega + a_w * dq[:, None]
        rot = rot @ _elementary(axis, q)
    return rot, omega, alpha


def _hip_acc_3d(body: _BodySplines, t: np.ndarray, side: float, half_width_m: float) -> np.ndarray:
    """Acceleration of a hip joint centre of the 3-D pelvis: the pelvis centre's (forward speed, lateral sway in
    the heading frame, height) plus the hip's rotation about it."""
    psi, dpsi, ddpsi = _eval3(body.heading, t)
    v, dv = body.speed(t), body.speed(t, 1)
    ddz = body.height(t, 2)
    s, ds, dds = _eval3(body.sway, t)
    zero = np.zeros_like(t)
    x_h = np.stack([np.cos(psi), np.sin(psi), zero], -1)
    y_h = np.stack([-np.sin(psi), np.cos(psi), zero], -1)
    # d(y_h)/dt = -dpsi x_h, d2(y_h)/dt2 = -ddpsi x_h - dpsi^2 y_h
    acc = (dv - 2 * ds * dpsi - s * ddpsi)[:, None] * x_h + (v * dpsi + dds - s * dpsi**2)[:, None] * y_h
    acc[:, 2] += ddz
    rot, om, al = _chain_motion(body, body.pelvis_links or (), t)
    return acc + _point_acc(rot, om, al, np.array([0.0, side * half_width_m, 0.0]))


def _point_acc(rot: np.ndarray, omega: np.ndarray, alpha: np.ndarray, r_local: np.ndarray) -> np.ndarray:
    r = rot @ r_local
    return np.cross(alpha, r) + np.cross(omega, np.cross(omega, r))


def _rollback_acc(rot: np.ndarray, omega: np.ndarray, alpha: np.ndarray, leg: _LegSplines, t: np.ndarray,
                  rollback_mm: float, stand_knee_deg: float) -> np.ndarray:
    """World acceleration (N, 3) of the joint centre's move along the thigh's x axis by ``rollback_mm`` per 90 deg
    of flexion above ``stand_knee_deg`` (:attr:`SimConfig.knee_rollback_mm`): with ``r = d(t) x_thigh`` in the
    thigh's frame, ``alpha x Rr + omega x (omega x Rr) + 2 omega x R dr/dt + R d2r/dt2``."""
    k = 1e-3 * rollback_mm / (np.pi / 2)
    q = leg.thigh(t) - leg.shank(t) - np.radians(stand_knee_deg)  # knee flexion [rad] above standing
    dq, ddq = leg.thigh(t, 1) - leg.shank(t, 1), leg.thigh(t, 2) - leg.shank(t, 2)
    x_w = rot[:, :, 0]
    r, dr, ddr = (k * q)[:, None] * x_w, (k * dq)[:, None] * x_w, (k * ddq)[:, None] * x_w
    return np.cross(alpha, r) + np.cross(omega, np.cross(omega, r)) + 2 * np.cross(omega, dr) + ddr


def _transient(t: np.ndarray, onsets: np.ndarray, amp: float, freq_hz: float, tau_s: float,
               deriv: int = 0) -> np.ndarray:
    """Sum of damped sines A exp(-u/tau) sin(2 pi f u), u = t - onset >= 0 (or its 1st/2nd derivative)."""
    out = np.zeros_like(t)
    if amp == 0 or len(onsets) == 0:
        return out
    w, a = 2 * np.pi * freq_hz, 1.0 / tau_s
    span = 8 * tau_s
    for t0 in onsets:
        i0, i1 = np.searchsorted(t, [t0, t0 + span])
        u = t[i0:i1] - t0
        e = np.exp(-a * u)
        s, c = np.sin(w * u), np.cos(w * u)
        if deriv == 0:
            out[i0:i1] += amp * e * s
        elif deriv == 1:
            out[i0:i1] += amp * e * (w * c - a * s)
        else:
            out[i0:i1] += amp * e * ((a * a - w * w) * s - 2 * a * w * c)
    return out


# ---------------------------------------------------------------------------------------------------------------
# Truth


def _crossings(t: np.ndarray, phase: np.ndarray, offset: float, mask: np.ndarray) -> np.ndarray:
    """Times where phase - offset crosses an integer while mask (walking) holds; linear within a grid step."""
    p = phase - offset
    k = np.floor(p)
    idx = np.nonzero((k[1:] > k[:-1]) & mask[1:] & mask[:-1])[0]
    frac = (k[idx + 1] - p[idx]) / (p[idx + 1] - p[idx])
    return t[idx] + frac * (t[idx + 1] - t[idx])


def _leg_truth(leg: str, tl: _Timeline, knee: np.ndarray, phase: np.ndarray, stance_frac: float) -> LegTruth:
    t = tl.t
    walking = tl.env > 0
    hs = _crossings(t, phase, 0.0, walking)
    to = _crossings(t, phase, stance_frac, walking)
    strides: list[TruthStride] = []
    bouts = [(b.t0, b.t1) for b in tl.bouts]
    for a, b in zip(hs[:-1], hs[1:], strict=False):
        same_bout = any(b0 - 1e-6 <= a and b <= b1 + 1e-6 for b0, b1 in bouts)
        tos = to[(to > a) & (to < b)]
        if not same_bout or len(tos) != 1:
            continue
        i0, i1 = np.searchsorted(t, [a, b])
        ito = int(np.searchsorted(t, tos[0]))
        seg = knee[i0:i1 + 1]
        # loading-response peak: first 60 % of stance, as pipeline.metrics.LOADING_SHARE
        stance = knee[i0: i0 + max(1, round(0.6 * (ito - i0))) + 1]
        steady = bool(np.all(tl.env[i0:i1 + 1] >= 1.0 - 1e-9))
        turning = bool(np.ptp(tl.heading_rad[i0:i1 + 1]) > np.radians(5))
        strides.append(TruthStride(
            leg=leg, t_start_s=float(a), t_end_s=float(b), t_toe_off_s=float(tos[0]),
            peak_swing_flexion_deg=float(knee[ito:i1 + 1].max()), min_flexion_deg=float(seg.min()),
            rom_deg=float(seg.max() - seg.min()), stance_flexion_deg=float(stance.max()),
            steady=steady, turning=turning))
    bout_ranges = []
    for b0, b1 in bouts:
        inb = hs[(hs >= b0 - 1e-6) & (hs <= b1 + 1e-6)]
        if len(inb):
            bout_ranges.append((float(inb[0]), float(inb[-1])))
    return LegTruth(leg, t, knee, hs, to, strides, bout_ranges)


# ---------------------------------------------------------------------------------------------------------------
# Sensors


def _sample_times(rng: np.random.Generator, cfg: SimConfig, fs: float, t_end: float
                  ) -> tuple[np.ndarray, np.ndarray, dict]:
    """True sample instants and reported timestamps of one sensor (before packet loss)."""
    drift = cfg.clock_drift_ppm * 1e-6 * rng.standard_normal()
    start = rng.uniform(0.0, 1.0 / fs) + rng.uniform(0.0, 0.05)
    n = int((t_end - 0.1 - start) * fs * (1 + drift))
    k = np.arange(n)
    t_true = start + k / (fs * (1 + drift))
    sync = cfg.sync_offset_ms * 1e-3 * rng.standard_normal()
    t_rep = start + sync + k / fs
    if t_rep[0] < 0:
        t_rep -= t_rep[0]
    return t_true, t_rep, {"drift_ppm": drift * 1e6, "sync_offset_ms": sync * 1e3, "start_s": start}


def gilbert_elliott_losses(rng: np.random.Generator, n_packets: int, mean_loss: float,
                           burst_packets: float) -> np.ndarray:
    """Lost packets (bool per packet) of a two-state Gilbert-Elliott channel (Gilbert 1960, Elliott 1963) with
    every packet lost in the bad state and none in the good one: bad-to-good probability r = 1 / burst_packets
    (geometric bursts of that mean length), good-to-bad p = r L / (1 - L) so the stationary loss is L."""
    lost = np.zeros(n_packets, dtype=bool)
    if mean_loss <= 0 or n_packets == 0:
        return lost
    r = 1.0 / max(1.0, burst_packets)
    p = min(1.0, r * mean_loss / (1.0 - min(mean_loss, 0.99)))
    u = rng.random(n_packets)
    bad = rng.random() < mean_loss  # start in the stationary distribution
    for i in range(n_packets):
        lost[i] = bad
        bad = (u[i] >= r) if bad else (u[i] < p)
    return lost


def _keep_mask(rng: np.random.Generator, cfg: SimConfig, fs: float, n: int,
               rng_burst: np.random.Generator | None = None) -> np.ndarray:
    keep = np.ones(n, dtype=bool)
    ps = max(1, cfg.packet_samples)
    n_packets = -(-n // ps)
    if cfg.loss_model == "bursty":
        lost = np.nonzero(gilbert_elliott_losses(rng_burst or rng, n_packets, cfg.packet_loss,
                                                 cfg.loss_burst_packets))[0]
    else:
        lost = np.nonzero(rng.random(n_packets) < cfg.packet_loss)[0]
    for p in lost:
        keep[p * ps:(p + 1) * ps] = False
    dur_min = n / fs / 60
    for _ in range(rng.poisson(cfg.outages_per_min * dur_min)):
        i0 = int(rng.integers(0, n))
        keep[i0: i0 + int(rng.uniform(0.3, 2.0) * fs)] = False
    keep[:ps] = True  # the first packet always arrives: it anchors the stream
    return keep


def _label(cfg: SimConfig, leg: str, seg: str) -> tuple[str, str]:
    """The (leg, segment) label the app gives a sensor physically on ``leg``/``seg`` (cfg.label_swap)."""
    other_leg = {"left": "right", "right": "left"}[leg]
    other_seg = {"thigh": "shank", "shank": "thigh"}[seg]
    swap = cfg.label_swap
    if swap == "legs" or (swap == "thighs" and seg == "thigh"):
        return other_leg, seg
    if swap == "segments" or (swap == "left_segments" and leg == "left"):
        return leg, other_seg
    return leg, seg


def _mounting(rng: np.random.Generator, cfg: SimConfig, leg: str, seg: str, left_mounts: dict) -> np.ndarray:
    """Sensor-to-segment rotation. Right-leg mountings are the sagittal mirror of the left ones plus a small
    random difference (a real patient does not place the two sides identically)."""
    if cfg.mounting == "aligned":
        return np.eye(3)
    if leg == "left" or seg not in left_mounts:
        r = _random_rotation(rng)
        left_mounts[seg] = r
        if leg == "left":
            return r
    m = np.diag([1.0, -1.0, 1.0])
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    perturb = _axis_angle(axis, np.array([np.radians(rng.uniform(0, 10))]))[0]
    return m @ left_mounts[seg] @ m @ perturb


def _add_pelvis_3d(body: _BodySplines, tl: _Timeline, level: float, rng: np.random.Generator) -> None:
    """The pelvis's rotation, obliquity and lateral sway in gait (``level`` x :class:`_OutOfPlane`, functions of
    the left leg's phase, zero outside gait) into ``body``."""
    op = _OUT_OF_PLANE
    scale = level * rng.uniform(0.7, 1.3, 3)
    ang = 2 * np.pi * tl.phase
    rot = -scale[0] * np.radians(op.pelvis_rot_deg) * np.cos(ang) * tl.env  # left side forward at left heel strike
    obl = scale[1] * np.radians(op.pelvis_obl_deg) * np.sin(ang) * tl.env  # left side up in left stance
    sway = scale[2] * op.pelvis_sway_m * np.sin(ang) * tl.env  # towards the left in left stance
    body.pelvis_links = ((2, make_interp_spline(tl.t, rot, k=5)), (0, make_interp_spline(tl.t, obl, k=5)))
    body.sway = make_interp_spline(tl.t, sway, k=5)


def _leg_chain_3d(body: _BodySplines, tl: _Timeline, leg: str, phase: np.ndarray, hip_deg: np.ndarray,
                  knee_deg: np.ndarray, stand_knee_deg: float, cfg: SimConfig, rng: np.random.Generator
                  ) -> tuple[_LegSplines, np.ndarray]:
    """One leg as a 3-D chain (module docstring): hip and knee each ``Ry(flexion) Rx(ab/adduction) Rz(rotation)``
    after the pelvis, with the typical curves (:data:`_HIP_ADD_PTS` ...) scaled by ``cfg.hip_3d`` / ``knee_3d``
    per subject and stride. Returns the leg's splines and its true knee angle [deg] (the chain's flexion)."""
    op = _OUT_OF_PLANE
    t, cyc, env = tl.t, phase % 1.0, tl.env
    side = 1.0 if leg == "left" else -1.0  # +y is lateral for the left leg: medial motion is -side * y

    def curve(points: tuple[tuple[float, float], ...], level: float) -> np.ndarray:
        amp = level * rng.uniform(0.7, 1.3) * (1 + _per_stride_signal(rng, phase, 0.1))
        return amp * _eval_fourier(_fourier_coefs(points), cyc) * env

    still = (1 - env) * cfg.hip_3d
    hip_add = curve(_HIP_ADD_PTS, cfg.hip_3d) - still * op.stand_hip_abd_deg
    hip_int = curve(_HIP_INT_PTS, cfg.hip_3d) - still * op.stand_hip_ext_rot_deg
    knee_add = curve(_KNEE_ADD_PTS, cfg.knee_3d) + cfg.knee_varus_deg
    coupling = cfg.knee_3d * op.knee_rot_per_flex * rng.uniform(0.7, 1.3)
    knee_int = curve(_KNEE_INT_PTS, cfg.knee_3d) + coupling * (knee_deg - stand_knee_deg)

    def spline(deg: np.ndarray) -> BSpline:
        return make_interp_spline(t, np.radians(deg), k=5)

    knee_sp = spline(knee_deg)
    thigh_links = (*(body.pelvis_links or ()), (1, spline(-hip_deg)), (0, spline(-side * hip_add)),
                   (2, spline(-side * hip_int)))
    shank_links = (*thigh_links, (1, knee_sp), (0, spline(-side * knee_add)), (2, spline(-side * knee_int)))
    sta = cfg.thigh_sta_deg * (knee_deg - stand_knee_deg) / 60.0  # the skin turns outwards as the knee flexes
    sensor_links = (*thigh_links, (2, spline(side * sta))) if cfg.thigh_sta_deg else thigh_links
    chain = _LegSplines(spline(hip_deg), spline(hip_deg - knee_deg), thigh_links, shank_links, sensor_links)
    return chain, np.degrees(knee_sp(t))


def simulate_session(cfg: SimConfig) -> SimSession:  # noqa: C901 - ditto: the draw order is part of every seed's output
    """Simulate one recording session; see the module docstring for the model."""
    if cfg.pattern not in _SPECS:
        raise ValueError(f"unknown pattern {cfg.pattern!r}; expected one of {PATTERNS}")
    spec = _SPECS[cfg.pattern]
    rng = np.random.default_rng(cfg.seed)
    tl = _build_timeline(cfg, spec, rng)
    t = tl.t

    knee_c = _fourier_coefs(spec.knee_pts)
    hip_c = _fourier_coefs(spec.hip_pts)
    subj_knee = float(np.clip(1 + 0.04 * rng.standard_normal(), 0.92, 1.08))
    subj_hip = float(np.clip(1 + 0.08 * rng.standard_normal(), 0.85, 1.15))
    var = cfg.variability

    # Posture between bouts: standing with slight sway, sitting at hip 90 / knee 90 deg.
    stand_knee = rng.uniform(2, 6)
    if cfg.stand_knee_deg is not None:
        stand_knee = float(cfg.stand_knee_deg)
    stand_hip = rng.uniform(0, 5)
    heading = tl.heading_rad + _smooth_noise(rng, t, np.radians(1.0), 2.0)
    height = tl.env * tl.pace * spec.bob_m * np.cos(4 * np.pi * tl.phase) - 0.45 * tl.sit
    if tl.moves.height is not None:
        height = height + tl.moves.height
    body = _BodySplines(
        heading=make_interp_spline(t, heading, k=5),
        speed=make_interp_spline(t, tl.env * tl.pace**1.5 * spec.speed_ms * (1 + 0.06 * np.cos(4 * np.pi * tl.phase)),
                                 k=5),
        height=make_interp_spline(t, height, k=5),
    )

    three_d = bool(cfg.knee_3d or cfg.hip_3d or cfg.knee_varus_deg or cfg.thigh_sta_deg)
    rng_3d = np.random.default_rng([cfg.seed, 5])  # the 3-D motion's own draws: the planar model is unchanged
    if three_d:
        _add_pelvis_3d(body, tl, cfg.hip_3d, rng_3d)
    legs: dict[str, _LegSplines] = {}
    truth: dict[str, LegTruth] = {}
    phases: dict[str, np.ndarray] = {}
    for leg in cfg.legs:
        phase = tl.phase + (0.0 if leg == "left" else 0.5)
        phases[leg] = phase
        s_knee = _eval_fourier(knee_c, phase % 1.0)
        s_min = s_knee.min()
        amp = subj_knee * tl.pace * (1 + _per_stride_signal(rng, phase, 0.025 * var))
        off = _per_stride_signal(rng, phase, 0.6 * var)
        gait_knee = s_min + amp * (s_knee - s_min) + off
        i_leg = 0 if leg == "left" else 1
        if cfg.knee_scale[i_leg] != 1.0 or cfg.knee_shift_deg[i_leg] != 0.0:
            gait_knee = s_min + cfg.knee_scale[i_leg] * amp * (s_knee - s_min) + off + cfg.knee_shift_deg[i_leg]
        leg_stand = stand_knee + cfg.stand_knee_right_extra_deg if leg == "right" else stand_knee
        gait_hip = subj_hip * tl.pace * _eval_fourier(hip_c, phase % 1.0) * (
            1 + _per_stride_signal(rng, phase, 0.03 * var))
        if cfg.hip_scale != 1.0:
            hip_mean = subj_hip * tl.pace * float(hip_c[0].real)
            gait_hip = hip_mean + cfg.hip_scale * (gait_hip - hip_mean)
        sway_k = _smooth_noise(rng, t, 0.7, 1.5)
        sway_h = _smooth_noise(rng, t, 0.7, 1.5)
        post_knee = (1 - tl.sit) * (leg_stand + sway_k) + tl.sit * (cfg.sit_knee_deg + sway_k)
        post_hip = (1 - tl.sit) * (stand_hip + sway_h) + tl.sit * (88.0 + sway_h)
        knee = tl.env * gait_knee + (1 - tl.env) * post_knee
        hip = tl.env * gait_hip + (1 - tl.env) * post_hip
        if tl.moves.height is not None:
            knee = knee + tl.moves.knee[leg]
            hip = hip + tl.moves.hip[leg]
        thigh = make_interp_spline(t, np.radians(hip), k=5)
        shank = make_interp_spline(t, np.radians(hip - knee), k=5)
        legs[leg] = _LegSplines(thigh, shank)
        knee_true = np.degrees(thigh(t) - shank(t))
        if three_d:
            legs[leg], knee_true = _leg_chain_3d(body, tl, leg, phase, hip, knee, leg_stand, cfg, rng_3d)
        truth[leg] = _leg_truth(leg, tl, knee_true, phase, spec.stance_frac)
        truth[leg].stand_knee_deg = float(leg_stand)

    thigh_len = rng.uniform(0.38, 0.46)
    half_width = rng.uniform(0.08, 0.11)
    streams: list[RawSensorStream] = []
    info: dict = {"sensors": {}, "thigh_length_m": thigh_len, "non_gait_s": list(tl.moves.non_gait_s)}
    impact_level = cfg.impact_level
    imp_freq, imp_tau = (_IMPACT_FREQ_HZ, _IMPACT_TAU_S) if cfg.impact_model == "default" else \
        (0.6 * _IMPACT_FREQ_HZ, 3.0 * _IMPACT_TAU_S)
    if cfg.impact_g is not None:  # the damped sine's peak, not its amplitude, is the shock in g
        impact_level = cfg.impact_g / (spec.impact_g * _damped_sine_peak(imp_freq, imp_tau))
    rng_burst = np.random.default_rng([cfg.seed, 3])
    left_mounts: dict[str, np.ndarray] = {}
    # Mountings draw from their own stream so "aligned" and "random" share identical kinematics and noise.
    rng_mount = np.random.default_rng([cfg.seed, 1])
    rng_loss = np.random.default_rng([cfg.seed, 2])  # likewise: loss settings change nothing but the loss
    rng_gain = np.random.default_rng([cfg.seed, 4])  # likewise for the sensitivity errors
    gyro_scale = 1.0 if cfg.gyro_unit == "deg/s" else np.pi / 180
    acc_scale = 1.0 if cfg.acc_unit == "m/s2" else 1.0 / GRAVITY_MS2
    for leg in cfg.legs:
        side = 1.0 if leg == "left" else -1.0  # +y is lateral for the left leg
        hs = truth[leg].heel_strikes_s
        if tl.moves.landings_s.size:
            hs = np.sort(np.concatenate([hs, tl.moves.landings_s]))  # a jump landing shocks like a heel strike
        for seg in ("thigh", "shank"):
            r_mount = _mounting(rng_mount, cfg, leg, seg, left_mounts)
            if seg == "thigh":
                lever = np.array([rng.uniform(-0.03, 0.05), side * rng.uniform(0.06, 0.09), rng.uniform(0.12, 0.25)])
            else:
                lever = np.array([rng.uniform(-0.02, 0.05), side * rng.uniform(0.04, 0.07),
                                  -rng.uniform(0.08, 0.22)])
            if cfg.lever_scale != 1.0 or cfg.lever_offaxis_m != 0.0:
                lever = cfg.lever_scale * lever + cfg.lever_offaxis_m * np.array([1.0, side, 0.0])
            fs = cfg.shank_fs_hz if seg == "shank" and cfg.shank_fs_hz else cfg.fs_hz
            t_true, t_rep, clock = _sample_times(rng, cfg, fs, t[-1])
            m = len(t_true)
            chain = legs[leg].thigh_links is not None
            if chain:
                rot_t, om_t, al_t = _chain_motion(body, legs[leg].thigh_links, t_true)
                acc_w = _hip_acc_3d(body, t_true, side, half_width)
            else:
                rot_t, om_t, al_t = _segment_motion(body, legs[leg].thigh, t_true)
                acc_w = _hip_acc(body, t_true, side, half_width)
            if seg == "thigh":
                if chain and legs[leg].thigh_sensor_links is not legs[leg].thigh_links:
                    # the skin turns about the femur's axis (through hip and knee): the lever turns with it
                    rot_t, om_t, al_t = _chain_motion(body, legs[leg].thigh_sensor_links, t_true)
                rot, om, _ = rot_t, om_t, al_t
                acc_w = acc_w + _point_acc(rot_t, om_t, al_t, lever + np.array([0, 0, -thigh_len]))
            else:
                rot, om, al = _chain_motion(body, legs[leg].shank_links, t_true) if chain else \
                    _segment_motion(body, legs[leg].shank, t_true)
                acc_w = acc_w + _point_acc(rot_t, om_t, al_t, np.array([0, 0, -thigh_len]))
                if cfg.knee_rollback_mm:
                    acc_w = acc_w + _rollback_acc(rot_t, om_t, al_t, legs[leg], t_true,
                                                  cfg.knee_rollback_mm, truth[leg].stand_knee_deg)
                acc_w = acc_w + _point_acc(rot, om, al, lever)
            f_w = acc_w + np.array([0.0, 0.0, GRAVITY_MS2])
            r_sensor = rot @ r_mount  # sensor-to-world
            gyr = np.einsum("nji,nj->ni", r_sensor, om)
            acc = np.einsum("nji,nj->ni", r_sensor, f_w)
            remount: dict = {}
            if cfg.remount_segment == seg and leg == "left" and cfg.remount_deg:
                gyr, acc, remount = _remounted(cfg, r_mount, t_true, t[-1] / 2, gyr, acc)

            # Transient rotation about a sensor-frame axis: soft-tissue wobble (thigh) or impact (shank).
            # Its angle returns to zero, so the integrated gyro keeps the true orientation on average.
            if seg == "thigh":
                rot_amp, rot_f, rot_tau = np.radians(0.8) * cfg.wobble_level, 11.0, 0.06
                tr_amp, imp_g = 0.0015 * cfg.wobble_level, 0.3 * spec.impact_g * impact_level
            else:
                # Heel contact arrests the shank's forward swing: a sharp backward rotation in the sagittal plane
                # right at heel strike, then a rebound (real shank gyro: local minimum ~10 ms after HS).
                rot_amp, rot_f, rot_tau = np.radians(0.5 * spec.impact_g) * impact_level, 12.0, 0.03
                if cfg.impact_g is not None:  # skin and strap limit the sensor's rocking whatever the shock
                    rot_amp = min(rot_amp, np.radians(_IMPACT_ROT_MAX_DEG))
                if cfg.impact_model == "ringing":  # a loose strap: larger, longer rocking
                    rot_amp, rot_tau = 2.0 * rot_amp, 3.0 * rot_tau
                tr_amp, imp_g = 0.0, spec.impact_g * impact_level
            axis = rng.standard_normal(3)
            axis /= np.linalg.norm(axis)
            if seg == "shank" and cfg.impact_model == "default":
                axis = r_mount.T @ np.array([0.0, 1.0, 0.0])
            if rot_amp > 0 and len(hs):
                ang = _transient(t_true, hs, rot_amp, rot_f, rot_tau)
                dang = _transient(t_true, hs, rot_amp, rot_f, rot_tau, deriv=1)
                rw = _axis_angle(axis, ang)
                gyr = np.einsum("nji,nj->ni", rw, gyr) + dang[:, None] * axis
                acc = np.einsum("nji,nj->ni", rw, acc)
            if tr_amp > 0 and len(hs):
                tdir = rng.standard_normal(3)
                tdir = tdir / np.linalg.norm(tdir)
                jolt = _transient(t_true, hs, tr_amp, 9.0, 0.07, deriv=2)
                acc += _balanced(jolt, t_true, hs, r_sensor, tdir) if cfg.impact_balanced else jolt[:, None] * tdir
            if imp_g > 0 and len(hs):
                # Heel-strike shock travels up the segment (mostly along its long axis, some anterior).
                d_seg = np.array([rng.uniform(0.1, 0.4), 0.0, 1.0])
                d_sensor = r_mount.T @ (d_seg / np.linalg.norm(d_seg))
                shock = _transient(t_true, hs, imp_g * GRAVITY_MS2, imp_freq, imp_tau)
                acc += _balanced(shock, t_true, hs, r_sensor, d_sensor) if cfg.impact_balanced else \
                    shock[:, None] * d_sensor
            off: dict = {}
            if cfg.off_body == "all" or cfg.off_body == leg:
                # the sensors sit on the segment's lateral side (lever arms above)
                skin_normal = r_mount.T @ np.array([0.0, side, 0.0])
                # one strap after the other: the thigh's first, the shank's when it lies on the table
                at_s = _off_body_at(truth, t[-1]) + (0.0 if seg == "thigh" else _OFF_BODY_MOVE_S + _OFF_BODY_NEXT_S)
                gyr, acc, off = _taken_off(cfg, leg, seg, r_sensor, skin_normal, t_true, at_s, gyr, acc)

            gbias = np.radians(cfg.gyro_bias_dps) * rng.standard_normal(3)
            gwalk = np.stack([_smooth_noise(rng, t_true, np.radians(cfg.gyro_bias_walk_dps), 20.0)
                              for _ in range(3)], -1)
            gyr = gyr + gbias + gwalk + np.radians(cfg.gyro_noise_dps) * rng.standard_normal((m, 3))
            abias = cfg.acc_bias_ms2 * rng.standard_normal(3)
            acc = acc + abias + cfg.acc_noise_ms2 * rng.standard_normal((m, 3))
            if cfg.gyro_gain_sd or cfg.acc_gain_sd:
                gyr = gyr * (1.0 + cfg.gyro_gain_sd * rng_gain.standard_normal(3))
                acc = acc * (1.0 + cfg.acc_gain_sd * rng_gain.standard_normal(3))

            if cfg.gyro_range_dps:  # saturation of the sensor's full-scale range
                gyr = np.clip(gyr, -np.radians(cfg.gyro_range_dps), np.radians(cfg.gyro_range_dps))
            if cfg.acc_range_g:
                acc = np.clip(acc, -cfg.acc_range_g * GRAVITY_MS2, cfg.acc_range_g * GRAVITY_MS2)
            keep = _keep_mask(rng_loss, cfg, fs, m, rng_burst)
            sid = f"{leg[0].upper()}-{seg}"
            label_leg, label_seg = _label(cfg, leg, seg)
            streams.append(RawSensorStream(
                sensor_id=sid, leg=label_leg, segment=label_seg, fs_hz=float(fs), t_s=t_rep[keep],
                gyr=np.degrees(gyr[keep]) * gyro_scale, acc=acc[keep] * acc_scale,
                gyro_unit=cfg.gyro_unit, acc_unit=cfg.acc_unit))
            info["sensors"][sid] = {"mounting": r_mount.tolist(), "lever_arm_m": lever.tolist(),
                                    "gyro_bias_dps": np.degrees(gbias).tolist(),
                                    "acc_bias_mps2": abias.tolist(), "dropped": int((~keep).sum()),
                                    **clock, **({"remount": remount} if remount else {}),
                                    **({"off_body": off} if off else {})}
    activity = "running" if cfg.pattern == "running" else "walking"
    return SimSession(cfg, activity, float(t[-1]), streams, truth, info)
