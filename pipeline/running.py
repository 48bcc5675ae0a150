"""Running: gait cycles from foot-strike impacts, the data windows that guide the calibration, impact masks and the
7 Hz low-pass (Rhudy et al. 2024, Sect. 2.2.2 and 3.1).

* Foot strikes are peaks of the UNFILTERED shank acceleration (Fig. 4). Rhudy et al. pick peaks of the magnitude,
  which works when the impacts tower over the swing accelerations; they do not always (soft shoes, forefoot
  strikers, a loosely coupled sensor: the swing "whip" of the shank reaches 3-4 g too). What always sets an impact
  apart is its frequency content, the ringing that the 7 Hz filter removes (Fig. 5), so the peaks are searched in
  the magnitude of the unfiltered signal's content above ``RunningParams.impact_hp_hz``.
* The joint axes and joint centres (Eq. 5) are fitted on 40-80 % of each gait cycle only (Fig. 7): swing, with its
  large sagittal rotation and no impact or ground-reaction effects. Going further than the paper, only the shank's
  axis comes from Eq. 2; the thigh's is its own dominant rotation axis over those windows
  (``RunningParams.thigh_axis``: a knee is no hinge, and with both axes free Eq. 2 tilts them together).
* Once the axes are known, gyroscope and accelerometer signals are low-passed with a 4th-order zero-lag 7 Hz
  Butterworth.
* Accelerometer measurement updates are skipped within +-5 % of the gait cycle around each foot strike (the filters
  run on the gyroscope alone there). Going further than the paper, the updates are limited to the same 40-80 %
  windows (plus quiet standing): the joint centres are fitted there, so that is where the lever-arm correction and
  hence the accelerometer angle are accurate; measured on the simulator, stance and terminal-swing updates pull the
  level of the estimate by 3-10 deg (bench/accuracy.py).

Pure functions over arrays (sample indices on the leg's uniform grid).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt

from pipeline.axes import (
    JointAxes,
    accelerometer_angle_deg,
    angular_acceleration,
    axis_up,
    centre_fit_step,
    fit_joint_axes,
    fit_joint_centres,
    fit_shank_axis,
    median_principal_axis,
    orient_axes,
    principal_axis,
    select_fit_samples,
)
from pipeline.constants import G_MPS2
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, PipelineParams, RunningParams
from pipeline.phases import detect_gait_events
from pipeline.posture import quiet_mask
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import ranges_mask, row_norm, true_runs
from pipeline.types import RunningDiagnostics

_RP = WALKING.running  # defaults of the public helpers; the leg flow passes its own preset's stage


@dataclass(frozen=True)
class RunningCycles:
    """Foot strikes of one leg and the gait cycles between them (sample indices)."""

    strikes: np.ndarray  # all detected foot strikes
    cycles: tuple[tuple[int, int], ...]  # (strike, next strike) pairs that form a plausible gait cycle
    stride_s: float  # median cycle length, NaN without cycles
    impact_g: float  # median high-frequency amplitude of the strike peaks, in g

    @property
    def n_cycles(self) -> int:
        return len(self.cycles)


def acc_magnitude(acc_mps2: np.ndarray) -> np.ndarray:
    """Row norms (N,) of accelerations (N, 3)."""
    return row_norm(np.asarray(acc_mps2, dtype=float).reshape(-1, 3))


def impact_signal(acc_shank_mps2: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                  params: RunningParams = _RP) -> np.ndarray:
    """Magnitude (N,) [m/s^2] of the unfiltered acceleration's content above ``impact_hp_hz``: the foot-strike
    ringing."""
    acc = np.asarray(acc_shank_mps2, dtype=float).reshape(-1, 3)
    if 0.45 * fs_hz <= params.impact_hp_hz:
        return acc_magnitude(acc - np.nanmedian(acc, axis=0))
    smooth = lowpass_7hz(acc, fs_hz, valid, cutoff_hz=params.impact_hp_hz, params=params)
    return acc_magnitude(acc - smooth)


def detect_foot_strikes(acc_shank_mps2: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                        params: RunningParams = _RP) -> np.ndarray:
    """Foot-strike sample indices: peaks of the unfiltered shank acceleration's impact content (Rhudy et al.,
    Fig. 4; :func:`impact_signal`).

    The impact level is the 99.5th percentile of that signal (the few samples of each impact dominate the top of the
    distribution whenever a good part of the session is running); peaks must exceed ``strike_rel`` of it and
    ``strike_min_g``, be at least ``min_stride_s / 2`` apart, and of two peaks closer than 60 % of the median
    interval only the higher is kept (the contralateral impact or a ringing after-shock)."""
    p = params
    mag = impact_signal(acc_shank_mps2, fs_hz, valid, p)
    n = mag.shape[0]
    ok = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool) & np.isfinite(mag)
    if n < 3 or not ok.any():
        return np.zeros(0, dtype=int)
    m = np.where(ok, mag, 0.0)
    level = float(np.percentile(m[ok], 99.5))
    height = max(p.strike_min_g * G_MPS2, p.strike_rel * level)
    peaks, _ = find_peaks(m, height=height, distance=max(1, int(0.5 * p.min_stride_s * fs_hz)))
    if peaks.size < 3:
        return peaks
    intervals = np.diff(peaks) / fs_hz
    plausible = intervals[(intervals >= p.min_stride_s) & (intervals <= p.max_stride_s)]
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


def gait_cycles(strikes: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                params: RunningParams = _RP) -> list[tuple[int, int]]:
    """Consecutive strike pairs that are one gait cycle: plausible length, consistent with their neighbours (within
    ``cycle_tol`` of the median of up to 5 neighbouring intervals) and no masked sample in between."""
    s = np.asarray(strikes, dtype=int)
    if s.size < 2:
        return []
    lengths = np.diff(s) / fs_hz
    ok = (lengths >= params.min_stride_s) & (lengths <= params.max_stride_s)
    padded = np.pad(np.where(ok, lengths, np.nan), 2, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 5)
    all_nan = np.isnan(windows).all(axis=1)
    with np.errstate(all="ignore"):
        local = np.nanmedian(np.where(all_nan[:, None], 1.0, windows), axis=1)
    ok &= np.abs(lengths - local) <= params.cycle_tol * local
    if valid is not None:
        inv_cum = np.concatenate(([0], np.cumsum(~np.asarray(valid, dtype=bool))))
        ok &= inv_cum[s[1:] + 1] == inv_cum[s[:-1]]
    return [(int(a), int(b)) for a, b, good in zip(s[:-1], s[1:], ok, strict=True) if good]


def find_cycles(acc_shank_mps2: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                params: RunningParams = _RP) -> RunningCycles:
    """Foot strikes and gait cycles of one leg from its shank accelerometer (N, 3) [m/s^2]."""
    strikes = detect_foot_strikes(acc_shank_mps2, fs_hz, valid, params)
    cycles = tuple(gait_cycles(strikes, fs_hz, valid, params))
    mag = impact_signal(acc_shank_mps2, fs_hz, valid, params)
    stride = float(np.median([(b - a) / fs_hz for a, b in cycles])) if cycles else float("nan")
    impact = float(np.median(mag[strikes])) / G_MPS2 if strikes.size else 0.0
    return RunningCycles(strikes=strikes, cycles=cycles, stride_s=stride, impact_g=impact)


def looks_like_running(cycles: RunningCycles, params: RunningParams = _RP) -> bool:
    """Running by cadence and impact magnitude: at least ``detect_min_cycles`` gait cycles, shorter than
    ``detect_max_stride_s`` and with foot-strike peaks above ``detect_min_impact_g``."""
    return (cycles.n_cycles >= params.detect_min_cycles and cycles.stride_s <= params.detect_max_stride_s
            and cycles.impact_g >= params.detect_min_impact_g)


def cycle_window_mask(cycles: tuple[tuple[int, int], ...] | list[tuple[int, int]], n: int,
                      lo: float = _RP.fit_window[0], hi: float = _RP.fit_window[1]) -> np.ndarray:
    """True on ``[lo, hi)`` of every gait cycle (Rhudy et al.: 40-80 % for the axis and centre optimisation)."""
    arr = np.asarray(cycles, dtype=int).reshape(-1, 2)
    span = arr[:, 1] - arr[:, 0]
    i0 = np.minimum(n, arr[:, 0] + np.round(lo * span).astype(int))
    i1 = np.minimum(n, arr[:, 0] + np.round(hi * span).astype(int))
    keep = i1 > i0
    return ranges_mask(n, i0[keep], i1[keep])


def impact_mask(strikes: np.ndarray, n: int, fs_hz: float, half_width: float = _RP.impact_half_width,
                stride_s: float | None = None, params: RunningParams = _RP) -> np.ndarray:
    """True within ``+-half_width`` of the gait cycle around every foot strike: the accelerometer must not update
    the filters there. The cycle length is the local interval to the neighbouring strikes (``stride_s`` or the
    median interval where a neighbour is missing or implausibly far)."""
    s = np.asarray(strikes, dtype=int)
    out = np.zeros(n, dtype=bool)
    if s.size == 0:
        return out
    intervals = np.diff(s) / fs_hz
    lo_s, hi_s = params.min_stride_s, params.max_stride_s
    good = intervals[(intervals >= lo_s) & (intervals <= hi_s)]
    typical = float(np.median(good)) if good.size else params.default_stride_s
    fallback = stride_s if stride_s and np.isfinite(stride_s) else typical
    before = np.concatenate(([np.nan], intervals))
    after = np.concatenate((intervals, [np.nan]))
    delta = np.zeros(n + 1, dtype=int)
    for k, p in enumerate(s.tolist()):
        cands = [v for v in (before[k], after[k]) if np.isfinite(v) and lo_s <= v <= hi_s]
        cycle = float(np.mean(cands)) if cands else fallback
        w = int(np.ceil(half_width * cycle * fs_hz))
        delta[max(0, p - w)] += 1
        delta[min(n, p + w + 1)] -= 1
    return np.cumsum(delta)[:-1] > 0


def lowpass_7hz(x: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                cutoff_hz: float = _RP.lowpass_hz, params: RunningParams = _RP) -> np.ndarray:
    """4th-order zero-lag Butterworth low-pass (Rhudy et al., Sect. 2.2.2, after Vasquez et al.), along axis 0 and
    separately per valid run so no gap is smeared; masked samples keep their input value."""
    x = np.asarray(x, dtype=float)
    out = x.copy()
    if cutoff_hz >= 0.5 * fs_hz:
        return out
    sos = butter(params.lowpass_order, cutoff_hz / (0.5 * fs_hz), output="sos")
    runs = [(0, x.shape[0])] if valid is None else true_runs(valid)
    for a, b in runs:
        if b - a > 3 * (2 * sos.shape[0] + 1):
            out[a:b] = sosfiltfilt(sos, x[a:b], axis=0)
    return out


# ---------------------------------------------------------------------------------------------------------------
# One running leg, prepared for the estimators (called by pipeline.session instead of its walking path).

def mean_cycle(x: np.ndarray, cycles: tuple[tuple[int, int], ...] | list[tuple[int, int]],
               n_points: int = 100) -> np.ndarray:
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


def shank_axis_sign(j2: np.ndarray, g2_rps: np.ndarray,
                    cycles: tuple[tuple[int, int], ...] | list[tuple[int, int]],
                    params: RunningParams = _RP) -> np.ndarray:
    """The sign of ``j2`` for running: the one under which the shank rotates forward (positive rate) over the late
    swing of the foot-strike cycle (``RunningParams.shank_swing_window``; Novacheck 1998). The walking convention
    (:func:`pipeline.axes.orient_axes`: the largest excursion positive) takes the swing peak for granted; in running
    the stance right after a rearfoot strike can turn the shank backwards faster than the swing turns it forwards,
    and the wrong sign makes the knee angle the sum of the two segments' angles. The foot strikes come from the
    shank accelerometer's impacts, so they do not depend on the sign."""
    if len(cycles) < 3:
        return j2
    m = mean_cycle(np.rad2deg(g2_rps @ j2), cycles)
    if not np.isfinite(m).all():
        return j2
    lo, hi = params.shank_swing_window
    late = m[int(round(lo * (m.size - 1))):int(round(hi * (m.size - 1))) + 1]
    return j2 if float(late.mean()) >= 0.0 else -j2


def thigh_axis_sign(j1: np.ndarray, j2: np.ndarray, g1_rps: np.ndarray, g2_rps: np.ndarray,
                    cycles: tuple[tuple[int, int], ...] | list[tuple[int, int]], fs_hz: float,
                    params: RunningParams = _RP) -> np.ndarray:
    """The sign of ``j1`` for running, from the timing of the knee's flexion peak within the foot-strike cycle.

    Eq. 2 fixes each axis only up to sign. With ``j2`` oriented (shank swing positive), the wrong ``j1`` turns the
    knee angle ``theta_thigh - theta_shank`` into ``-(theta_thigh + theta_shank)``, which peaks at toe-off (~40 %,
    both segments furthest back) instead of mid-swing (~70 %). The walking rule
    (:func:`pipeline.axes.orient_thigh_on_gait`) rests on walking's gait events; this one on the foot-strike cycles
    that running is processed by."""
    if len(cycles) < 3:
        return j1
    best, best_dist = j1, np.inf
    for cand in (j1, -j1):
        angle = np.cumsum(np.rad2deg(g1_rps @ cand - g2_rps @ j2)) / fs_hz
        m = mean_cycle(angle, cycles)
        if not np.isfinite(m).all():
            return j1
        phase = float(np.argmax(m)) / (m.size - 1)
        lo, hi = params.swing_peak_phase
        inside = lo <= phase <= hi
        dist = abs(phase - params.swing_peak_target) - (1.0 if inside else 0.0)
        if dist < best_dist:
            best, best_dist = cand, dist
    return best


def filtered_leg(prep: PreparedLeg, params: RunningParams = _RP) -> PreparedLeg:
    """The leg with gyroscopes and accelerometers through the 7 Hz zero-lag low-pass (Rhudy et al., Sect. 2.2.2)."""
    def f(x: np.ndarray) -> np.ndarray:
        return lowpass_7hz(x, prep.fs_hz, prep.valid, cutoff_hz=params.lowpass_hz, params=params)

    return replace(prep, gyr_thigh_rps=f(prep.gyr_thigh_rps), gyr_shank_rps=f(prep.gyr_shank_rps),
                   acc_thigh_mps2=f(prep.acc_thigh_mps2), acc_shank_mps2=f(prep.acc_shank_mps2))


# ---------------------------------------------------------------------------------------------------------------
# One running leg, prepared for the estimators (pipeline.session calls this instead of pipeline.walking).

def build_running_leg_input(prep: PreparedLeg, params: PipelineParams, cycles: RunningCycles | None = None
                            ) -> tuple[LegInput, RunningDiagnostics]:
    """Rhudy et al.'s running flow (Fig. 3) for one leg: foot strikes from the unfiltered shank accelerometer ->
    joint axes (:func:`_running_axes`) on 40-80 % of each gait cycle -> 7 Hz low-pass -> joint centres (Eq. 5) on
    the same windows -> accelerometer angle (Eq. 6-7) -> impact mask for the filters' measurement updates.

    The leg input carries ``running_cycles``, ``acc_update_mask`` (True on the 40-80 % windows and quiet periods,
    never within +-5 % of a foot strike) and the quiet mask of the unfiltered leg. Falls back to the whole valid
    recording for the fits when fewer than 3 cycles are found."""
    rp = params.running
    fs, valid, n = prep.fs_hz, prep.valid, prep.n
    if cycles is None:
        cycles = find_cycles(prep.acc_shank_mps2, fs, valid, rp)
    fit_mask = cycle_window_mask(cycles.cycles, n, *rp.fit_window) & valid
    if fit_mask.sum() < 3 * fs or cycles.n_cycles < 3:
        fit_mask = valid.copy()
    axes = _running_axes(prep, fit_mask, cycles, params)
    filt = filtered_leg(prep, rp)
    g1, g2 = filt.gyr_thigh_rps, filt.gyr_shank_rps
    rate = np.rad2deg(g1 @ axes.j1 - g2 @ axes.j2)
    shank_sag = np.rad2deg(g2 @ axes.j2)
    rate[~valid] = np.nan
    shank_sag[~valid] = np.nan
    events = detect_gait_events(shank_sag, fs, valid, shank_acc_mps2=prep.acc_shank_mps2, params=params.phases)
    a1, a2 = filt.acc_thigh_mps2, filt.acc_shank_mps2
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    idx = select_fit_samples(g1, g2, fit_mask, params.axes, step=centre_fit_step(fs, params.axes))
    centres = fit_joint_centres(a1[idx], g1[idx], gd1[idx], a2[idx], g2[idx], gd2[idx], axes.j1, axes.j2,
                                params.axes)
    acc_angle = accelerometer_angle_deg(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, centres)
    acc_angle[~valid] = np.nan
    impacts = impact_mask(cycles.strikes, n, fs, rp.impact_half_width, stride_s=cycles.stride_s, params=rp)
    quiet = quiet_mask(prep, params.posture)
    update = (fit_mask | quiet) & ~impacts
    leg = LegInput(prep=filt, axes=axes, centres=centres, rate_dps=rate, acc_angle_deg=acc_angle,
                   shank_sag_dps=shank_sag, events=events, params=params, activity="running",
                   running_cycles=cycles.cycles, acc_update_mask=update, quiet_mask=quiet, prefiltered=True,
                   unfiltered=prep)
    diag = RunningDiagnostics(foot_strikes=int(cycles.strikes.size), cycles=cycles.n_cycles,
                              stride_s=None if np.isnan(cycles.stride_s) else round(cycles.stride_s, 3),
                              impact_g=round(cycles.impact_g, 2),
                              impact_masked_pct=round(100 * float(impacts.mean()), 1),
                              acc_update_pct=round(100 * float(update.mean()), 1))
    return leg, diag


def _running_axes(prep: PreparedLeg, fit_mask: np.ndarray, cycles: RunningCycles, params: PipelineParams
                  ) -> JointAxes:
    """The knee axes on the fit windows (``RunningParams.thigh_axis``); signs from whole strides (within 40-80 %
    thigh and shank may rotate in opposite senses): the shank's from its late-swing rotation
    (:func:`shank_axis_sign`), the thigh's from the timing of the flexion peak (:func:`thigh_axis_sign`)."""
    valid = prep.valid
    g1_all, g2_all = prep.gyr_thigh_rps, prep.gyr_shank_rps
    window = np.flatnonzero(fit_mask)
    if params.running.thigh_axis == "principal" and window.size >= 10:
        j1 = median_principal_axis(g1_all, true_runs(fit_mask))  # one run per cycle's window
        # evenly over the windows, not select_fit_samples' most dynamic samples: those are where the segments'
        # other rotations peak too, and the shank's axis fitted there leaned 7 deg further off on the 3-D runs
        idx = window[::int(np.ceil(window.size / params.axes.max_fit_samples))]
        j2, rms = fit_shank_axis(g1_all[idx], g2_all[idx], j1, principal_axis(g2_all[window]))
        axes = JointAxes(j1=j1, j2=j2, rms_residual_dps=rms, n_samples=int(idx.size))
    else:
        axes = fit_joint_axes(g1_all, g2_all, fit_mask, params.axes, up=axis_up(prep, params.axes))
    j1, j2 = orient_axes(axes.j1, axes.j2, g1_all[valid], g2_all[valid])
    j2 = shank_axis_sign(j2, g2_all, cycles.cycles, params.running)
    j1 = thigh_axis_sign(j1, j2, g1_all, g2_all, cycles.cycles, prep.fs_hz, params.running)
    return replace(axes, j1=j1, j2=j2)


def detect_running(prep: PreparedLeg, params: RunningParams = _RP) -> RunningCycles | None:
    """The leg's gait cycles when the recording looks like running (cadence and impacts), else None: for sessions
    declared ``unknown``."""
    cycles = find_cycles(prep.acc_shank_mps2, prep.fs_hz, prep.valid, params)
    return cycles if looks_like_running(cycles, params) else None
