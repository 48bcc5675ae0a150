"""Running: gait cycles from foot-strike impacts, the data windows that guide the calibration, impact masks and the
7 Hz low-pass (Rhudy et al. 2024, Sect. 2.2.2 and 3.1).

* Foot strikes are peaks of the UNFILTERED shank acceleration (Fig. 4). Rhudy et al. pick peaks of the magnitude,
  which works when the impacts tower over the swing accelerations; they do not always (soft shoes, forefoot
  strikers, a loosely coupled sensor: the swing "whip" of the shank reaches 3-4 g too). What always sets an impact
  apart is its frequency content, the ringing that the 7 Hz filter removes (Fig. 5), so the peaks are searched in
  the magnitude of the unfiltered signal's content above ``IMPACT_HP_HZ``.
* The joint axes (Eq. 2) and joint centres (Eq. 5) are fitted on 40-80 % of each gait cycle only (Fig. 7): swing,
  with its large sagittal rotation and no impact or ground-reaction effects.
* Once the axes are known, gyroscope and accelerometer signals are low-passed with a 4th-order zero-lag 7 Hz
  Butterworth.
* Accelerometer measurement updates are skipped within +-5 % of the gait cycle around each foot strike (the filters
  run on the gyroscope alone there). Going further than the paper, the updates are limited to the same 40-80 %
  windows (plus quiet standing): the joint centres are fitted there, so that is where the lever-arm correction and
  hence the accelerometer angle are accurate; measured on the simulator, stance and terminal-swing updates pull the
  level of the estimate by 3-10 deg (see bench/accuracy.py).

Pure functions over arrays (sample indices on the leg's uniform grid).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt

from pipeline.axes import (
    accelerometer_angle_deg,
    angular_acceleration,
    fit_joint_axes,
    fit_joint_centres,
    orient_axes,
    select_fit_samples,
)
from pipeline.estimators import LegData
from pipeline.estimators.kf import quiet_mask
from pipeline.phases import detect_gait_events
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import row_norm, true_runs

G_MPS2 = 9.80665
FIT_WINDOW = (0.40, 0.80)  # fraction of the gait cycle used for the axis and centre optimisation
IMPACT_HALF_WIDTH = 0.05  # fraction of the gait cycle skipped on either side of a foot strike
LOWPASS_HZ = 7.0
LOWPASS_ORDER = 4
MIN_STRIDE_S, MAX_STRIDE_S = 0.45, 1.6  # one running stride (same foot to same foot)
IMPACT_HP_HZ = 12.0
STRIKE_MIN_G = 0.5  # an impact's high-frequency peak is at least this large (g)
STRIKE_REL = 0.4  # ... and at least this share of the session's impact level
CYCLE_TOL = 0.35  # a cycle whose length is off the local median by more than this share is not a gait cycle
# Running vs walking: runners strike the ground every ~0.6-0.8 s with 4-10 g at the shank; walkers every 0.9-1.4 s
# with 1.5-3 g.
RUNNING_MAX_STRIDE_S = 0.85
RUNNING_MIN_IMPACT_G = 1.0  # high-frequency impact amplitude
RUNNING_MIN_CYCLES = 6


@dataclass
class RunningCycles:
    """Foot strikes of one leg and the gait cycles between them (sample indices)."""

    strikes: np.ndarray  # all detected foot strikes
    cycles: list[tuple[int, int]]  # (strike, next strike) pairs that form a plausible gait cycle
    stride_s: float  # median cycle length, NaN without cycles
    impact_g: float  # median high-frequency amplitude of the strike peaks, in g

    @property
    def n_cycles(self) -> int:
        return len(self.cycles)


def acc_magnitude(acc_mps2: np.ndarray) -> np.ndarray:
    return row_norm(np.asarray(acc_mps2, dtype=float).reshape(-1, 3))


def impact_signal(acc_shank_mps2: np.ndarray, fs_hz: float, valid: np.ndarray | None = None) -> np.ndarray:
    """Magnitude (m/s^2) of the unfiltered acceleration's content above ``IMPACT_HP_HZ``: the foot-strike ringing."""
    acc = np.asarray(acc_shank_mps2, dtype=float).reshape(-1, 3)
    if 0.45 * fs_hz <= IMPACT_HP_HZ:
        return acc_magnitude(acc - np.nanmedian(acc, axis=0))
    smooth = lowpass_7hz(acc, fs_hz, valid, cutoff_hz=IMPACT_HP_HZ)
    return acc_magnitude(acc - smooth)


def detect_foot_strikes(acc_shank_mps2: np.ndarray, fs_hz: float, valid: np.ndarray | None = None) -> np.ndarray:
    """Foot-strike sample indices: peaks of the unfiltered shank acceleration's impact content (Rhudy et al.,
    Fig. 4; :func:`impact_signal`).

    The impact level is the 99.5th percentile of that signal (the few samples of each impact dominate the top of the
    distribution whenever a good part of the session is running); peaks must exceed ``STRIKE_REL`` of it and
    ``STRIKE_MIN_G``, be at least ``MIN_STRIDE_S / 2`` apart, and of two peaks closer than 60 % of the median
    interval only the higher is kept (the contralateral impact or a ringing after-shock)."""
    mag = impact_signal(acc_shank_mps2, fs_hz, valid)
    n = mag.shape[0]
    ok = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool) & np.isfinite(mag)
    if n < 3 or not ok.any():
        return np.zeros(0, dtype=int)
    m = np.where(ok, mag, 0.0)
    level = float(np.percentile(m[ok], 99.5))
    height = max(STRIKE_MIN_G * G_MPS2, STRIKE_REL * level)
    peaks, _ = find_peaks(m, height=height, distance=max(1, int(0.5 * MIN_STRIDE_S * fs_hz)))
    if peaks.size < 3:
        return peaks
    intervals = np.diff(peaks) / fs_hz
    plausible = intervals[(intervals >= MIN_STRIDE_S) & (intervals <= MAX_STRIDE_S)]
    if plausible.size == 0:
        return peaks
    min_gap = int(0.6 * float(np.median(plausible)) * fs_hz)
    kept: list[int] = []
    for p in peaks.tolist():
        if kept and p - kept[-1] < min_gap:
            if m[p] > m[kept[-1]]:
                kept[-1] = p
            continue
        kept.append(p)
    return np.asarray(kept, dtype=int)


def gait_cycles(strikes: np.ndarray, fs_hz: float, valid: np.ndarray | None = None) -> list[tuple[int, int]]:
    """Consecutive strike pairs that are one gait cycle: plausible length, consistent with their neighbours (within
    ``CYCLE_TOL`` of the median of up to 5 neighbouring intervals) and no masked sample in between."""
    s = np.asarray(strikes, dtype=int)
    if s.size < 2:
        return []
    lengths = np.diff(s) / fs_hz
    ok = (lengths >= MIN_STRIDE_S) & (lengths <= MAX_STRIDE_S)
    padded = np.pad(np.where(ok, lengths, np.nan), 2, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 5)
    all_nan = np.isnan(windows).all(axis=1)
    with np.errstate(all="ignore"):
        local = np.nanmedian(np.where(all_nan[:, None], 1.0, windows), axis=1)
    ok &= np.abs(lengths - local) <= CYCLE_TOL * local
    if valid is not None:
        inv_cum = np.concatenate(([0], np.cumsum(~np.asarray(valid, dtype=bool))))
        ok &= inv_cum[s[1:] + 1] == inv_cum[s[:-1]]
    return [(int(a), int(b)) for a, b, good in zip(s[:-1], s[1:], ok, strict=True) if good]


def find_cycles(acc_shank_mps2: np.ndarray, fs_hz: float, valid: np.ndarray | None = None) -> RunningCycles:
    """Foot strikes and gait cycles of one leg from its shank accelerometer."""
    strikes = detect_foot_strikes(acc_shank_mps2, fs_hz, valid)
    cycles = gait_cycles(strikes, fs_hz, valid)
    mag = impact_signal(acc_shank_mps2, fs_hz, valid)
    stride = float(np.median([(b - a) / fs_hz for a, b in cycles])) if cycles else float("nan")
    impact = float(np.median(mag[strikes])) / G_MPS2 if strikes.size else 0.0
    return RunningCycles(strikes=strikes, cycles=cycles, stride_s=stride, impact_g=impact)


def looks_like_running(cycles: RunningCycles) -> bool:
    """Running by cadence and impact magnitude: enough gait cycles, shorter than ``RUNNING_MAX_STRIDE_S`` and with
    foot-strike peaks above ``RUNNING_MIN_IMPACT_G``."""
    return (cycles.n_cycles >= RUNNING_MIN_CYCLES and cycles.stride_s <= RUNNING_MAX_STRIDE_S
            and cycles.impact_g >= RUNNING_MIN_IMPACT_G)


def cycle_window_mask(cycles: list[tuple[int, int]], n: int, lo: float = FIT_WINDOW[0],
                      hi: float = FIT_WINDOW[1]) -> np.ndarray:
    """True on ``[lo, hi)`` of every gait cycle (Rhudy et al.: 40-80 % for the axis and centre optimisation)."""
    delta = np.zeros(n + 1, dtype=int)
    for a, b in cycles:
        i0 = min(n, a + int(round(lo * (b - a))))
        i1 = min(n, a + int(round(hi * (b - a))))
        if i1 > i0:
            delta[i0] += 1
            delta[i1] -= 1
    return np.cumsum(delta)[:-1] > 0


def impact_mask(strikes: np.ndarray, n: int, fs_hz: float, half_width: float = IMPACT_HALF_WIDTH,
                stride_s: float | None = None) -> np.ndarray:
    """True within ``+-half_width`` of the gait cycle around every foot strike: the accelerometer must not update
    the filters there. The cycle length is the local interval to the neighbouring strikes (``stride_s`` or the
    median interval where a neighbour is missing or implausibly far)."""
    s = np.asarray(strikes, dtype=int)
    out = np.zeros(n, dtype=bool)
    if s.size == 0:
        return out
    intervals = np.diff(s) / fs_hz
    good = intervals[(intervals >= MIN_STRIDE_S) & (intervals <= MAX_STRIDE_S)]
    fallback = stride_s if stride_s and np.isfinite(stride_s) else (float(np.median(good)) if good.size else 0.7)
    before = np.concatenate(([np.nan], intervals))
    after = np.concatenate((intervals, [np.nan]))
    delta = np.zeros(n + 1, dtype=int)
    for k, p in enumerate(s.tolist()):
        cands = [v for v in (before[k], after[k]) if np.isfinite(v) and MIN_STRIDE_S <= v <= MAX_STRIDE_S]
        cycle = float(np.mean(cands)) if cands else fallback
        w = int(np.ceil(half_width * cycle * fs_hz))
        delta[max(0, p - w)] += 1
        delta[min(n, p + w + 1)] -= 1
    return np.cumsum(delta)[:-1] > 0


def lowpass_7hz(x: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                cutoff_hz: float = LOWPASS_HZ) -> np.ndarray:
    """4th-order zero-lag Butterworth low-pass (Rhudy et al., Sect. 2.2.2, after Vasquez et al.), along axis 0 and
    separately per valid run so no gap is smeared; masked samples keep their input value."""
    x = np.asarray(x, dtype=float)
    out = x.copy()
    if cutoff_hz >= 0.5 * fs_hz:
        return out
    sos = butter(LOWPASS_ORDER, cutoff_hz / (0.5 * fs_hz), output="sos")
    runs = [(0, x.shape[0])] if valid is None else true_runs(valid)
    for a, b in runs:
        if b - a > 3 * (2 * sos.shape[0] + 1):
            out[a:b] = sosfiltfilt(sos, x[a:b], axis=0)
    return out


# ---------------------------------------------------------------------------------------------------------------
# One running leg, prepared for the estimators (called by pipeline.session instead of its walking path).

SWING_PEAK_PHASE = (0.55, 0.9)  # running knee flexion peaks at ~70 % of the cycle (Novacheck 1998)


def mean_cycle(x: np.ndarray, cycles: list[tuple[int, int]], n_points: int = 100) -> np.ndarray:
    """Average of ``x`` over the gait cycles, each resampled to ``n_points`` and with its linear trend removed (so a
    gyroscope integral's drift does not matter)."""
    grid = np.linspace(0.0, 1.0, n_points)
    rows = []
    for a, b in cycles:
        seg = x[a:b + 1]
        if not np.isfinite(seg).all():
            continue
        seg = seg - np.linspace(seg[0], seg[-1], seg.size)
        rows.append(np.interp(grid, np.linspace(0.0, 1.0, seg.size), seg))
    return np.mean(rows, axis=0) if rows else np.full(n_points, np.nan)


def thigh_axis_sign(j1: np.ndarray, j2: np.ndarray, g1_rps: np.ndarray, g2_rps: np.ndarray,
                    cycles: list[tuple[int, int]], fs_hz: float) -> np.ndarray:
    """The sign of ``j1`` for running, from the timing of the knee's flexion peak within the foot-strike cycle.

    Eq. 2 fixes each axis only up to sign. With ``j2`` oriented (shank swing positive), the wrong ``j1`` turns the
    knee angle ``theta_thigh - theta_shank`` into ``-(theta_thigh + theta_shank)``, which peaks at toe-off (~40 %,
    both segments furthest back) instead of mid-swing (~70 %). The walking rule (thigh and shank rates correlated)
    is unreliable in running, where the shank whips forward while the thigh is already braking."""
    if len(cycles) < 3:
        return j1
    best, best_dist = j1, np.inf
    for cand in (j1, -j1):
        angle = np.cumsum(np.rad2deg(g1_rps @ cand - g2_rps @ j2)) / fs_hz
        m = mean_cycle(angle, cycles)
        if not np.isfinite(m).all():
            return j1
        phase = float(np.argmax(m)) / (m.size - 1)
        inside = SWING_PEAK_PHASE[0] <= phase <= SWING_PEAK_PHASE[1]
        dist = abs(phase - 0.7) - (1.0 if inside else 0.0)
        if dist < best_dist:
            best, best_dist = cand, dist
    return best


def filtered_leg(prep: PreparedLeg) -> PreparedLeg:
    """The leg with gyroscopes and accelerometers through the 7 Hz zero-lag low-pass (Rhudy et al., Sect. 2.2.2)."""
    def f(x: np.ndarray) -> np.ndarray:
        return lowpass_7hz(x, prep.fs_hz, prep.valid)

    return replace(prep, gyr_thigh_rps=f(prep.gyr_thigh_rps), gyr_shank_rps=f(prep.gyr_shank_rps),
                   acc_thigh_mps2=f(prep.acc_thigh_mps2), acc_shank_mps2=f(prep.acc_shank_mps2))


def build_running_leg_data(prep: PreparedLeg, cycles: RunningCycles | None = None) -> tuple[LegData, dict]:
    """Rhudy et al.'s running flow (Fig. 3) for one leg: foot strikes from the unfiltered shank accelerometer ->
    joint axes (Eq. 2) on 40-80 % of each gait cycle -> 7 Hz low-pass -> joint centres (Eq. 5) on the same windows ->
    accelerometer angle (Eq. 6-7) -> impact mask for the filters' measurement updates.

    Same outputs as :func:`pipeline.session.build_leg_data`; ``extras`` carries ``running_cycles`` and
    ``acc_update_mask`` (True on the 40-80 % windows and quiet periods, never within +-5 % of a foot strike).
    Falls back to the whole valid recording for the fits when fewer than 3 cycles are found."""
    fs, valid, n = prep.fs_hz, prep.valid, prep.n
    if cycles is None:
        cycles = find_cycles(prep.acc_shank_mps2, fs, valid)
    fit_mask = cycle_window_mask(cycles.cycles, n) & valid
    if fit_mask.sum() < 3 * fs or cycles.n_cycles < 3:
        fit_mask = valid.copy()
    axes = fit_joint_axes(prep.gyr_thigh_rps, prep.gyr_shank_rps, fit_mask)
    # the sign convention needs whole strides (within 40-80 % thigh and shank may rotate in opposite senses)
    axes.j1, axes.j2 = orient_axes(axes.j1, axes.j2, prep.gyr_thigh_rps[valid], prep.gyr_shank_rps[valid])
    axes.j1 = thigh_axis_sign(axes.j1, axes.j2, prep.gyr_thigh_rps, prep.gyr_shank_rps, cycles.cycles, fs)
    filt = filtered_leg(prep)
    g1, g2 = filt.gyr_thigh_rps, filt.gyr_shank_rps
    rate = np.rad2deg(g1 @ axes.j1 - g2 @ axes.j2)
    shank_sag = np.rad2deg(g2 @ axes.j2)
    rate[~valid] = np.nan
    shank_sag[~valid] = np.nan
    events = detect_gait_events(shank_sag, fs, valid, shank_acc_mps2=prep.acc_shank_mps2)
    a1, a2 = filt.acc_thigh_mps2, filt.acc_shank_mps2
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    idx = select_fit_samples(g1, g2, fit_mask)
    centres = fit_joint_centres(a1[idx], g1[idx], gd1[idx], a2[idx], g2[idx], gd2[idx], axes.j1, axes.j2)
    acc_angle = accelerometer_angle_deg(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, centres)
    acc_angle[~valid] = np.nan
    impacts = impact_mask(cycles.strikes, n, fs, stride_s=cycles.stride_s)
    quiet = quiet_mask(prep)
    update = (fit_mask | quiet) & ~impacts
    data = LegData(prep=filt, axes=axes, centres=centres, rate_dps=rate, acc_angle_deg=acc_angle,
                   shank_sag_dps=shank_sag, events=events, activity="running",
                   extras={"acc_update_mask": update, "running_cycles": cycles.cycles, "quiet_mask": quiet})
    info = {"j1": np.round(axes.j1, 4).tolist(), "j2": np.round(axes.j2, 4).tolist(),
            "axis_rms_residual_dps": round(axes.rms_residual_dps, 2), "axis_fit_samples": axes.n_samples,
            "o1_m": np.round(centres.o1, 4).tolist(), "o2_m": np.round(centres.o2, 4).tolist(),
            "centre_rms_residual_mps2": round(centres.rms_residual_mps2, 3),
            "bouts": int(events.bout.max() + 1) if events.bout.size else 0, "bridged_gaps": prep.bridged_gaps,
            "running": {"foot_strikes": int(cycles.strikes.size), "cycles": cycles.n_cycles,
                        "stride_s": None if np.isnan(cycles.stride_s) else round(cycles.stride_s, 3),
                        "impact_g": round(cycles.impact_g, 2),
                        "impact_masked_pct": round(100 * float(impacts.mean()), 1),
                        "acc_update_pct": round(100 * float(update.mean()), 1)}}
    return data, info


def detect_running(prep: PreparedLeg) -> RunningCycles | None:
    """The leg's gait cycles when the recording looks like running (cadence and impacts), else None: for sessions
    declared ``unknown``."""
    cycles = find_cycles(prep.acc_shank_mps2, prep.fs_hz, prep.valid)
    return cycles if looks_like_running(cycles) else None


RUNNING_AUTO_ESTIMATOR = "ekf"


def running_auto(data: LegData) -> tuple[np.ndarray, np.ndarray, list[tuple[str, float, tuple[str, ...]]], dict]:
    """The ``auto`` policy for running legs: the EKF of Rhudy et al. Eq. 22-24 with the running inputs (impact-free
    40-80 % updates, per-stride gyro de-biasing, quiet-standing anchoring, automatic tuning; see
    :mod:`pipeline.estimators.kf` and :mod:`pipeline.estimators.ekf`). GO's zero-angle update does not apply: a
    running knee never straightens (minimum ~15-25 deg).

    Rhudy et al. found KF and CF slightly better than their EKF (Table 2, Vicon-tuned). With these inputs and no
    reference tuning the EKF came out best on the simulator (bench/accuracy.py, running, TUNE seeds 0-9 at 100 and
    200 Hz: RMSE EKF 2.17, KF 2.57, CF 3.35 deg; per-stride peak LoA EKF -6.9..5.0, KF -5.5..7.5): its update
    ``P |a| |b| / (P |a|^2 + r) sin(alpha_acc - x)`` bounds the pull of a large accelerometer-angle error (the sine)
    and weighs it by the acceleration magnitudes.

    Returns angle, per-sample estimator names, one ``(estimator, quality, reasons)`` per gait-event stride, and
    diagnostics."""
    from pipeline.estimators.ekf import ekf_leg
    from pipeline.estimators.kf import acc_zero_deg

    name = RUNNING_AUTO_ESTIMATOR
    angle = ekf_leg(data)
    labels = np.where(np.isfinite(angle), name, "").astype(str)
    reasons: tuple[str, ...] = () if acc_zero_deg(data) != 0.0 else ("no_absolute_reference",)
    quality = 0.8 if reasons else 1.0
    choices = [(name, quality, reasons) for _ in data.events.strides]
    return angle, labels, choices, {"running_tuning": data.extras.get("ekf_tuning")}
