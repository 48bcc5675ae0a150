"""Thigh/shank clock offset and drift of one leg, and the leg prepared again with the shank's stamps corrected.

Two constraints of Seel et al. 2014 carry the timing: the hinge (Eq. 2; :func:`pipeline.axes.estimate_sync_lag_s`)
and the joint centre (Eq. 5; :func:`pipeline.axes.estimate_centre_lag_s`). Neither holds on every knee. A real knee
is no hinge: the tibia turns about its long axis as the knee flexes and ab/adducts a few degrees, and the
gait-locked misfit reads as a lag (5-15 ms on the simulator's ``joint_3d`` axis; -10 / -18 ms on the
hardware-synchronised biomechZoo trial). Such a knee shows itself in the hinge fit, whose axes lean towards the
segments' long axes (``pipeline.axes.JointAxes.leaning``): its timing then comes from the joint centre. The
joint-centre constraint needs rigid segments, which a heel-strike shock ringing through the shank is not for
~0.1 s: those samples are left out (:func:`shock_mask`). Where the knee is a hinge, the hinge cue is the more precise
of the two and is used wherever it speaks (out-of-plane motion: turns, hip ab/adduction).

A 10-15 ms offset, common between two BLE sensors, would otherwise distort swing flexion by several degrees.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.axes import (
    JointAxes,
    angular_acceleration,
    axis_up,
    estimate_centre_lag_s,
    estimate_sync_lag_s,
    fit_joint_axes,
    fit_margin_mask,
    hinge_rates,
)
from pipeline.constants import G_MPS2
from pipeline.params import AxesParams, PipelineParams, SyncParams
from pipeline.prepare import SI, PreparedLeg, nominal_fs, prepare_leg_si, to_si
from pipeline.signal_utils import lowpass_runs_many, row_norm
from pipeline.types import RawSensorStream
from pipeline.walking import fit_gyros, reusable_thigh_fit


@dataclass(frozen=True)
class SyncedLeg:
    """A prepared leg with its axes and the clock model applied to the shank (None when not applied)."""

    prep: PreparedLeg
    axes: JointAxes
    shank_lag_ms: float | None  # offset at mid-session
    shank_drift_ppm: float | None
    fit_gyr: tuple[np.ndarray, np.ndarray] | None  # :func:`pipeline.walking.fit_gyros` of ``prep`` when computed
    thigh_fit: np.ndarray | None = None  # else its thigh half when known (:func:`pipeline.walking.reusable_thigh_fit`)


def synchronised_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, params: PipelineParams,
                     si: tuple[SI, SI] | None = None) -> SyncedLeg:
    """Prepare a leg, fit its axes, and when the hinge constraint shows a thigh/shank clock offset larger than
    ``SyncParams.min_shift_samples`` of a sample, prepare it again with the shank's time stamps corrected (the axes
    do not move with the lag). ``si``: both streams' :func:`pipeline.prepare.to_si` when the caller has them
    (never modified). Raises ValueError with less than a second of usable samples."""
    si1, si2 = (to_si(thigh), to_si(shank)) if si is None else si
    fs1 = nominal_fs(thigh, si1[0]) if si1[0].size else 0.0
    fs2 = nominal_fs(shank, si2[0]) if si2[0].size else 0.0
    prep = prepare_leg_si(leg, si1, si2, fs1, fs2, params=params.prepare, posture=params.posture)
    if prep.valid.sum() < max(10, int(prep.fs_hz)):
        raise ValueError("less than one second of usable samples")
    g1, g2 = fit_gyros(prep, params.axes.fit_cutoff_hz)
    fit_gyr: tuple[np.ndarray, np.ndarray] | None = (g1, g2)
    axes = fit_joint_axes(g1, g2, prep.valid, params.axes, up=axis_up(prep, params.axes),
                          gd2_rps2=angular_acceleration(g2, prep.fs_hz) if params.axes.fit_lag else None)
    offset, drift = clock_model(prep, g1, g2, axes, params.sync, params.axes)
    if offset is None:
        return SyncedLeg(prep, axes, None, None, fit_gyr)
    # lag(t) = offset + drift * (t - t_mid): shift the shank's stamps back by it
    t_mid = float(prep.t_s[prep.n // 2])
    if max(abs(offset), abs(drift) * (prep.t_s[-1] - prep.t_s[0]) / 2) * prep.fs_hz > params.sync.min_shift_samples:
        first = prep
        prep = prepare_leg_si(leg, si1, si2, fs1, fs2, shank_shift_s=-(offset - drift * t_mid),
                              shank_drift=-drift, reuse=first, params=params.prepare,
                              posture=params.posture)
        return SyncedLeg(prep, axes, round(1000 * offset, 1), round(1e6 * drift, 1), None,
                         reusable_thigh_fit(first, prep, g1))
    return SyncedLeg(prep, axes, round(1000 * offset, 1), round(1e6 * drift, 1), fit_gyr)


def clock_model(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                axes_params: AxesParams | None = None) -> tuple[float | None, float]:
    """Shank-vs-thigh lag at mid-session [s] and its drift [s/s]: one lag per ``window_s`` window and a straight line
    through them (rate error clipped to ``max_drift``), applied only when at least two windows are informative and
    agree with the line within ``agree_s``. The hinge constraint's lags where the knee moves as a hinge and they
    speak; the joint-centre constraint's (when ``axes_params`` is given) where the hinge's own fit leans towards the
    segments' long axes (``JointAxes.leaning``: the tibia turns as the knee flexes, and the
    gait-locked misfit reads as a lag) or where the hinge constraint is silent (straight walking, jumps: no
    out-of-plane motion). Hinge windows that speak but disagree mark a leg whose timing is not to be trusted (no
    correction). A leg shorter than two windows gets a constant lag from the joint-centre cue on its halves
    (:func:`_short_session_lag`). ``g1``, ``g2``: low-passed gyros (N, 3) [rad/s]."""
    fs = prep.fs_hz
    win = int(params.window_s * fs)
    if prep.n < 2 * win:
        return _short_session_lag(prep, g1, g2, axes, params, axes_params), 0.0
    edges = np.linspace(0, prep.n, int(prep.n // win) + 1).astype(int)
    windows = [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    if not axes.leaning:
        h1, h2 = axes.hinge()
        rates = hinge_rates(g1, g2, h1, h2)  # once for all windows
        hinge = [estimate_sync_lag_s(g1, g2, h1, h2, prep.valid, fs, window=w, rates=rates,
                                     max_lag_s=params.max_lag_s) for w in windows]
        offset, drift = _line_model(prep, windows, params, lambda w: hinge[windows.index(w)])
        # on a hinge knee the centre cue is the less accurate of the two wherever turns make both informative
        # (sweep and accuracy tune seeds: crouch gait, long lever arms)
        if offset is not None or axes_params is None or sum(lag is not None for lag in hinge) >= 2:
            return offset, drift
    elif axes_params is None:
        return None, 0.0
    pick = np.unique(np.linspace(0, len(windows) - 1, min(len(windows), params.max_centre_windows)).round())
    return _line_model(prep, [windows[int(i)] for i in pick], params,
                       _centre_lag_of(prep, g1, g2, axes, params, axes_params))


def _short_session_lag(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                       axes_params: AxesParams | None) -> float | None:
    """Constant lag [s] of a leg too short for two ``window_s`` windows (a 10 m walk test, a 30-60 s trial): the
    joint-centre cue (Seel Eq. 5) on its two halves, applied only when both are informative and agree within
    ``agree_s`` (the rule of :func:`_line_model`) and their lag exceeds ``short_min_lag_s``; halves shorter than
    ``short_window_s`` give no estimate. Not the hinge cue (Eq. 2): on the hardware-synchronised biomechZoo trial
    (10 s) it reads a false -10 / -18 ms and follows only a quarter of an imposed offset, where the centre cue
    follows it one to one. Two halves fix no drift: over such a session two crystals (up to ~200 ppm apart) move the
    lag by 6 ms at most."""
    half = prep.n // 2
    if axes_params is None or half < params.short_window_s * prep.fs_hz:
        return None
    halves = [slice(0, half), slice(half, prep.n)]
    lag = _line_model(prep, halves, params, _centre_lag_of(prep, g1, g2, axes, params, axes_params))[0]
    return lag if lag is not None and abs(lag) > params.short_min_lag_s else None


def _centre_lag_of(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                   axes_params: AxesParams) -> Callable[[slice], float | None]:
    """The joint-centre lag of one window (:func:`pipeline.axes.estimate_centre_lag_s`), its inputs prepared once."""
    fs = prep.fs_hz
    a1, a2 = (np.nan_to_num(a) for a in lowpass_runs_many((prep.acc_thigh_mps2, prep.acc_shank_mps2), prep.valid,
                                                            axes_params.fit_cutoff_hz, fs))
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    far = fit_margin_mask(prep.valid, fs, axes_params)
    far &= ~shock_mask(((prep.acc_thigh_mps2, a1), (prep.acc_shank_mps2, a2)), prep.valid, fs, params)
    # the first window that fits centres hands them on: the others start from them (one fit, no restarts, each)
    centres: list[np.ndarray] = []

    def lag_of(w: slice) -> float | None:
        lag, fitted = estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, far, fs, w,
                                            params.max_lag_s, axes_params, centres[0] if centres else None)
        if fitted is not None and not centres:
            centres.append(fitted)
        return lag
    return lag_of


def shock_mask(acc: tuple[tuple[np.ndarray, np.ndarray], ...], valid: np.ndarray, fs_hz: float,
               params: SyncParams) -> np.ndarray:
    """(N,) bool: within ``shock_s`` of a sample where a segment's acceleration departs from its low-passed self
    (``acc``: pairs of raw and low-passed (N, 3) [m/s^2]) by more than ``shock_g``: a heel-strike or landing shock,
    ringing above the gait band, during which the two accelerometers do not measure one rigid knee-centre
    acceleration (Seel Eq. 5)."""
    shock = np.zeros(valid.shape[0], dtype=bool)
    for raw, low in acc:
        shock |= row_norm(np.nan_to_num(raw) - low) > params.shock_g * G_MPS2
    shock &= valid
    if not shock.any():
        return shock
    half = int(np.ceil(params.shock_s * fs_hz))
    return np.convolve(shock.astype(float), np.ones(2 * half + 1), mode="same") > 0


def _line_model(prep: PreparedLeg, windows: list[slice], params: SyncParams,
                lag_of: Callable[[slice], float | None]) -> tuple[float | None, float]:
    """Offset at mid-session and drift of the window lags ``lag_of(window)``; None unless at least two windows are
    informative and all agree with the line within ``agree_s``."""
    t_mid = float(prep.t_s[prep.n // 2])
    pts = []
    for w in windows:
        lag = lag_of(w)
        if lag is not None:
            pts.append((float(prep.t_s[(w.start + w.stop) // 2]) - t_mid, lag))
    if len(pts) < 2:
        return None, 0.0
    t, lag = np.array(pts).T
    # a line through two points always "agrees": two windows give a constant offset, three or more a drift too
    drift = float(np.clip(np.polyfit(t, lag, 1)[0], -params.max_drift, params.max_drift)) if len(pts) >= 3 else 0.0
    offset = float(np.median(lag - drift * t))
    if np.max(np.abs(lag - offset - drift * t)) > params.agree_s:
        return None, 0.0
    return offset, drift
