"""One session in, knee flexion per leg and per stride out: the pipeline's single public entry point.

prepare (units, common grid, gaps) -> joint axes (Seel Eq. 2) -> knee rate and shank sagittal rate -> gait events
(Allseits) -> joint centres and accelerometer angle (Seel Eq. 5-7) -> estimator(s) -> per-stride metrics.
"""

from __future__ import annotations

import warnings as _warnings
from collections.abc import Sequence

import numpy as np

from pipeline import ALGORITHM_VERSION
from pipeline.axes import (
    JointAxes,
    accelerometer_angle_deg,
    angular_acceleration,
    estimate_sync_lag_s,
    fit_joint_axes,
    fit_joint_centres,
    hinge_rates,
    select_fit_samples,
)
from pipeline.estimators import LegData, get_estimator
from pipeline.estimators.cf import complementary_filter
from pipeline.estimators.go import go_relative
from pipeline.fusion import fuse
from pipeline.metrics import stride_values
from pipeline.phases import detect_gait_events
from pipeline.prepare import PreparedLeg, nominal_fs, prepare_leg_si, to_si
from pipeline.running import RUNNING_AUTO_ESTIMATOR, build_running_leg_data, detect_running, running_auto
from pipeline.signal_utils import lowpass_runs_many
from pipeline.types import LegResult, RawSensorStream, SessionResult, StrideMetrics

SYNC_WINDOW_S = 40.0
MAX_DRIFT = 150e-6  # BLE sensor crystals: tens of ppm; more is a bad estimate
SYNC_AGREE_S = 0.006
FIT_CUTOFF_HZ = 10.0  # gyro/acc smoothing for the axis and joint-centre fits and the accelerometer angle


def process_session(streams: Sequence[RawSensorStream], activity: str = "walking",
                    estimator: str = "auto") -> SessionResult:
    """Knee flexion of every leg that has both a thigh and a shank stream.

    ``estimator``: ``"auto"`` (GO with absolute zero, CF fallback per stride, :mod:`pipeline.fusion`) or the name of
    one registered estimator (``"go"``, ``"cf"``, ...) run alone on the same prepared data.
    Raises ValueError only for unusable input (no streams, no samples, unknown estimator).
    """
    if estimator != "auto":
        get_estimator(estimator)  # fail early on an unknown name
    if not streams:
        raise ValueError("the session has no sensor streams")
    if all(np.asarray(s.t_s).size == 0 for s in streams):
        raise ValueError("the session has no samples")
    warnings: list[str] = []
    by_leg: dict[str, dict[str, RawSensorStream]] = {}
    for s in streams:
        slot = by_leg.setdefault(s.leg, {})
        if s.segment in slot:
            keep = max(slot[s.segment], s, key=lambda x: np.asarray(x.t_s).size)
            warnings.append(f"{s.leg} {s.segment}: several sensors ({slot[s.segment].sensor_id}, {s.sensor_id}); "
                            f"using {keep.sensor_id}")
            slot[s.segment] = keep
        else:
            slot[s.segment] = s
    legs: dict[str, LegResult] = {}
    for leg in sorted(by_leg):
        segs = by_leg[leg]
        if "thigh" not in segs or "shank" not in segs:
            missing = "thigh" if "thigh" not in segs else "shank"
            warnings.append(f"{leg} leg skipped: no {missing} sensor")
            continue
        try:
            legs[leg] = process_leg(leg, segs["thigh"], segs["shank"], activity, estimator)
        except ValueError as exc:
            warnings.append(f"{leg} leg skipped: {exc}")
    return SessionResult(algorithm_version=ALGORITHM_VERSION, activity=activity, legs=legs, warnings=warnings)


def _dps(x: np.ndarray) -> np.ndarray:
    return np.rad2deg(x)


def synchronised_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream
                     ) -> tuple[PreparedLeg, JointAxes, dict, tuple[np.ndarray, np.ndarray] | None]:
    """Prepare a leg, fit its axes, and when the hinge constraint shows a thigh/shank clock offset larger than a
    quarter sample, prepare it again with the shank's time stamps corrected (the axes do not move with the lag).
    A 10-15 ms offset, common between two BLE sensors, would otherwise distort swing flexion by several degrees.
    The last item: the FIT_CUTOFF_HZ-filtered gyros of the returned ``prep`` when they were already computed
    (no re-preparation), for :func:`build_leg_data` to reuse; None otherwise."""
    si1, si2 = to_si(thigh), to_si(shank)
    fs1 = nominal_fs(thigh, si1[0]) if si1[0].size else 0.0
    fs2 = nominal_fs(shank, si2[0]) if si2[0].size else 0.0
    prep = prepare_leg_si(leg, si1, si2, fs1, fs2)
    if prep.valid.sum() < max(10, int(prep.fs_hz)):
        raise ValueError("less than one second of usable samples")
    g1, g2 = (np.nan_to_num(g) for g in lowpass_runs_many((prep.gyr_thigh_rps, prep.gyr_shank_rps), prep.valid,
                                                            FIT_CUTOFF_HZ, prep.fs_hz))
    fit_gyr: tuple[np.ndarray, np.ndarray] | None = (g1, g2)
    axes = fit_joint_axes(g1, g2, prep.valid)
    offset, drift = _clock_model(prep, g1, g2, axes)
    info = {"shank_lag_ms": None if offset is None else round(1000 * offset, 1),
            "shank_drift_ppm": None if offset is None else round(1e6 * drift, 1)}
    if offset is not None:
        # lag(t) = offset + drift * (t - t_mid): shift the shank's stamps back by it
        t_mid = float(prep.t_s[prep.n // 2])
        if max(abs(offset), abs(drift) * (prep.t_s[-1] - prep.t_s[0]) / 2) * prep.fs_hz > 0.25:
            prep = prepare_leg_si(leg, si1, si2, fs1, fs2, shank_shift_s=-(offset - drift * t_mid),
                                  shank_drift=-drift, reuse=prep)
            fit_gyr = None
    return prep, axes, info, fit_gyr


def _clock_model(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes) -> tuple[float | None, float]:
    """Shank-vs-thigh lag at mid-session and its drift [s/s]: one lag per SYNC_WINDOW_S window (Seel Eq. 2 hinge
    constraint, :func:`pipeline.axes.estimate_sync_lag_s`) and a straight line through them (rate error clipped to
    MAX_DRIFT). Applied only when at least two windows are informative and agree with the line within
    SYNC_AGREE_S: a real knee is not a perfect hinge, and on the hardware-synchronised biomechZoo trial (one 10 s
    window) the constraint alone suggests a false 10-18 ms lag, so a single unconfirmed estimate is not used."""
    fs = prep.fs_hz
    win = int(SYNC_WINDOW_S * fs)
    t_mid = float(prep.t_s[prep.n // 2])
    if prep.n < 2 * win:
        return None, 0.0
    edges = np.linspace(0, prep.n, int(prep.n // win) + 1).astype(int)
    pts = []
    rates = hinge_rates(g1, g2, axes.j1, axes.j2)  # once for all windows
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        lag = estimate_sync_lag_s(g1, g2, axes.j1, axes.j2, prep.valid, fs, window=slice(a, b), rates=rates)
        if lag is not None:
            pts.append((float(prep.t_s[(a + b) // 2]) - t_mid, lag))
    if len(pts) < 2:
        return None, 0.0
    t, lag = np.array(pts).T
    # a line through two points always "agrees": two windows give a constant offset, three or more a drift too
    drift = float(np.clip(np.polyfit(t, lag, 1)[0], -MAX_DRIFT, MAX_DRIFT)) if len(pts) >= 3 else 0.0
    offset = float(np.median(lag - drift * t))
    if np.max(np.abs(lag - offset - drift * t)) > SYNC_AGREE_S:
        return None, 0.0
    return offset, drift


def build_leg_data(prep: PreparedLeg, activity: str = "walking", axes: JointAxes | None = None,
                   fit_gyr: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[LegData, dict]:
    """Axes (unless given), rates, events, joint centres and accelerometer angle of one prepared leg.
    ``fit_gyr``: the FIT_CUTOFF_HZ-filtered thigh and shank gyros of this very ``prep`` (NaN-free), when already
    computed (:func:`synchronised_leg`), so the same filter is not run twice."""
    valid = prep.valid
    fs = prep.fs_hz
    if fit_gyr is None:
        g1, g2 = (np.nan_to_num(g) for g in lowpass_runs_many((prep.gyr_thigh_rps, prep.gyr_shank_rps), valid,
                                                                FIT_CUTOFF_HZ, fs))
    else:
        g1, g2 = fit_gyr
    if axes is None:
        axes = fit_joint_axes(g1, g2, valid)
    rate = _dps(prep.gyr_thigh_rps @ axes.j1 - prep.gyr_shank_rps @ axes.j2)
    shank_sag = _dps(prep.gyr_shank_rps @ axes.j2)
    rate[~valid] = np.nan
    shank_sag[~valid] = np.nan
    events = detect_gait_events(shank_sag, fs, valid, shank_acc_mps2=prep.acc_shank_mps2)
    a1, a2 = (np.nan_to_num(a) for a in lowpass_runs_many((prep.acc_thigh_mps2, prep.acc_shank_mps2), valid,
                                                            FIT_CUTOFF_HZ, fs))
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    # joint centres only tell standing from sitting (upright test of the standing reference, pipeline.fusion):
    # their in-plane directions are too uncertain for the absolute zero itself
    # away from masked gaps: the filters and Eq. 1 differences are unreliable within a few samples of one
    margin = max(int(0.1 * fs), 1)
    far = ~np.convolve(~valid, np.ones(2 * margin + 1), mode="same").astype(bool)
    idx = select_fit_samples(g1, g2, far)
    centres = fit_joint_centres(a1[idx], g1[idx], gd1[idx], a2[idx], g2[idx], gd2[idx], axes.j1, axes.j2)
    acc_angle = accelerometer_angle_deg(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, centres)
    acc_angle[~valid] = np.nan
    data = LegData(prep=prep, axes=axes, centres=centres, rate_dps=rate, acc_angle_deg=acc_angle,
                   shank_sag_dps=shank_sag, events=events, activity=activity)
    info = {"j1": np.round(axes.j1, 4).tolist(), "j2": np.round(axes.j2, 4).tolist(),
            "axis_rms_residual_dps": round(axes.rms_residual_dps, 2), "axis_fit_samples": axes.n_samples,
            "o1_m": np.round(centres.o1, 4).tolist(), "o2_m": np.round(centres.o2, 4).tolist(),
            "centre_rms_residual_mps2": round(centres.rms_residual_mps2, 3),
            "bouts": int(events.bout.max() + 1) if events.bout.size else 0,
            "bridged_gaps": prep.bridged_gaps}
    return data, info


def process_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, activity: str = "walking",
                estimator: str = "auto") -> LegResult:
    with _warnings.catch_warnings():
        _warnings.simplefilter("ignore", RuntimeWarning)
        prep, axes, sync_info, fit_gyr = synchronised_leg(leg, thigh, shank)
        cycles = detect_running(prep) if activity == "unknown" else None
        if activity == "running" or cycles is not None:
            data, info = build_running_leg_data(prep, cycles)
        else:
            data, info = build_leg_data(prep, activity, axes=axes, fit_gyr=fit_gyr)
        info.update(sync_info)
        strides = data.events.strides
        if estimator == "auto" and data.activity == "running":
            angle, labels, choices, auto_info = running_auto(data)
            info.update(auto_info)
        elif estimator == "auto":
            go_rel, diag = go_relative(data)
            data.extras["go"] = diag
            cf = complementary_filter(data.rate_dps, data.acc_angle_deg, prep.fs_hz, prep.valid)
            fused = fuse(data, go_rel, diag, cf)
            angle, labels = fused.angle_deg, fused.estimator
            choices = [(c.estimator, c.quality, c.reasons) for c in fused.choices]
            info.update(fused.info)
        else:
            angle = np.asarray(get_estimator(estimator)(data), dtype=float)
            labels = np.where(np.isfinite(angle), estimator, "").astype(str)
            choices = [(estimator, 1.0, ()) for _ in strides]
    primary = RUNNING_AUTO_ESTIMATOR if data.activity == "running" else "go"
    out: list[StrideMetrics] = []
    # non-finite samples counted by prefix sum: one pass instead of a test per stride
    bad_cum = np.concatenate(([0], np.cumsum(~np.isfinite(angle))))
    for (a, t, b), (name, quality, reasons) in zip(strides, choices, strict=True):
        if bad_cum[b + 1] != bad_cum[a]:
            continue
        v = stride_values(angle, prep.t_s, a, t, b)
        out.append(StrideMetrics(leg=leg, index=len(out), estimator=name, quality=float(quality),
                                 quality_reasons=tuple(reasons), activity=data.activity,
                                 fallback=estimator == "auto" and name != primary, **v.__dict__))
    walking_s = float(sum(s.duration_s for s in out))
    info["n_strides"] = len(out)
    return LegResult(leg=leg, fs_hz=prep.fs_hz, t_s=prep.t_s, angle_deg=angle, estimator=labels, strides=out,
                     gaps_s=list(prep.gaps_s), walking_s=walking_s, activity=data.activity, info=info)
