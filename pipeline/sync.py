"""Thigh/shank clock offset and drift of one leg from Seel's hinge constraint (Seel et al. 2014, Eq. 2;
:func:`pipeline.axes.estimate_sync_lag_s`), and the leg prepared again with the shank's stamps corrected.

A 10-15 ms offset, common between two BLE sensors, would otherwise distort swing flexion by several degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.axes import JointAxes, estimate_sync_lag_s, fit_joint_axes, hinge_rates
from pipeline.params import PipelineParams, SyncParams
from pipeline.prepare import PreparedLeg, nominal_fs, prepare_leg_si, to_si
from pipeline.types import RawSensorStream
from pipeline.walking import fit_gyros


@dataclass(frozen=True)
class SyncedLeg:
    """A prepared leg with its axes and the clock model applied to the shank (None when not applied)."""

    prep: PreparedLeg
    axes: JointAxes
    shank_lag_ms: float | None  # offset at mid-session
    shank_drift_ppm: float | None
    fit_gyr: tuple[np.ndarray, np.ndarray] | None  # :func:`pipeline.walking.fit_gyros` of ``prep`` when computed


def synchronised_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, params: PipelineParams) -> SyncedLeg:
    """Prepare a leg, fit its axes, and when the hinge constraint shows a thigh/shank clock offset larger than
    ``SyncParams.min_shift_samples`` of a sample, prepare it again with the shank's time stamps corrected (the axes
    do not move with the lag). Raises ValueError with less than a second of usable samples."""
    si1, si2 = to_si(thigh), to_si(shank)
    fs1 = nominal_fs(thigh, si1[0]) if si1[0].size else 0.0
    fs2 = nominal_fs(shank, si2[0]) if si2[0].size else 0.0
    prep = prepare_leg_si(leg, si1, si2, fs1, fs2, params=params.prepare)
    if prep.valid.sum() < max(10, int(prep.fs_hz)):
        raise ValueError("less than one second of usable samples")
    g1, g2 = fit_gyros(prep, params.axes.fit_cutoff_hz)
    fit_gyr: tuple[np.ndarray, np.ndarray] | None = (g1, g2)
    axes = fit_joint_axes(g1, g2, prep.valid, params.axes)
    offset, drift = clock_model(prep, g1, g2, axes, params.sync)
    if offset is None:
        return SyncedLeg(prep, axes, None, None, fit_gyr)
    # lag(t) = offset + drift * (t - t_mid): shift the shank's stamps back by it
    t_mid = float(prep.t_s[prep.n // 2])
    if max(abs(offset), abs(drift) * (prep.t_s[-1] - prep.t_s[0]) / 2) * prep.fs_hz > params.sync.min_shift_samples:
        prep = prepare_leg_si(leg, si1, si2, fs1, fs2, shank_shift_s=-(offset - drift * t_mid),
                              shank_drift=-drift, reuse=prep, params=params.prepare)
        fit_gyr = None
    return SyncedLeg(prep, axes, round(1000 * offset, 1), round(1e6 * drift, 1), fit_gyr)


def clock_model(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams
                ) -> tuple[float | None, float]:
    """Shank-vs-thigh lag at mid-session [s] and its drift [s/s]: one lag per ``window_s`` window and a straight line
    through them (rate error clipped to ``max_drift``). Applied only when at least two windows are informative and
    agree with the line within ``agree_s``: a real knee is not a perfect hinge, and on the hardware-synchronised
    biomechZoo trial (one 10 s window) the constraint alone suggests a false 10-18 ms lag, so a single unconfirmed
    estimate is not used. ``g1``, ``g2``: low-passed gyros (N, 3) [rad/s]."""
    fs = prep.fs_hz
    win = int(params.window_s * fs)
    t_mid = float(prep.t_s[prep.n // 2])
    if prep.n < 2 * win:
        return None, 0.0
    edges = np.linspace(0, prep.n, int(prep.n // win) + 1).astype(int)
    pts = []
    rates = hinge_rates(g1, g2, axes.j1, axes.j2)  # once for all windows
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        lag = estimate_sync_lag_s(g1, g2, axes.j1, axes.j2, prep.valid, fs, window=slice(a, b), rates=rates,
                                  max_lag_s=params.max_lag_s)
        if lag is not None:
            pts.append((float(prep.t_s[(a + b) // 2]) - t_mid, lag))
    if len(pts) < 2:
        return None, 0.0
    t, lag = np.array(pts).T
    # a line through two points always "agrees": two windows give a constant offset, three or more a drift too
    drift = float(np.clip(np.polyfit(t, lag, 1)[0], -params.max_drift, params.max_drift)) if len(pts) >= 3 else 0.0
    offset = float(np.median(lag - drift * t))
    if np.max(np.abs(lag - offset - drift * t)) > params.agree_s:
        return None, 0.0
    return offset, drift
