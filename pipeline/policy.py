"""The ``auto`` policy: which estimator's angle each stride keeps, its quality, and whether it is a fallback.

**Walking**: GO (Allseits et al. 2018) made ABSOLUTE per stride, with a complementary-filter (Seel et al. 2014,
Rhudy et al. 2024 Eq. 17) fallback for strides where GO's assumptions fail. No paper does this part. GO's
zero-angle update assumes the knee is straight at the minimum before swing, so a crouch or contracture knee that
never extends would read 0 deg there. Each stride's GO curve is therefore made absolute: by the mean of (gravity
knee - GO) over its mid-stance, the gravity knee being the angle between the two segments' gravity directions in the
joint plane with gravity from the stride's mean specific force (:mod:`pipeline.cycle_gravity`: over a stride each
segment's velocity returns, so that mean is gravity, free of joint-centre, lever-arm, impact and soft-tissue terms)
carried to each sample by the gyros; where the stride gives none (a hole, a clipped sample, a jump), by its
gravity-levelled neighbours' level interpolated in time (``FusionParams.gravity_min_cycles``), and where the
leg has too few of those, by the mean of (accelerometer angle - GO) over the calm samples of its mid-stance (Seel
Eq. 6-7 angle).
Both take their zero from quiet upright standing (:func:`pipeline.posture.standing_reference`). The per-stride
offsets are smoothed with a running median over neighbouring strides (the true minimum flexion changes slowly) and
interpolated between stride centres so the trace is continuous. Without standing in the session the offset stays 0
(Allseits' assumption) and the stride says so (``no_absolute_reference``). The trace is GO inside the strides that
kept it, CF (shifted to the same zero) elsewhere: fallback strides, bout edges, standing, sitting, transitions.

**Running**: the EKF of Rhudy et al. Eq. 22-24 with the running inputs (impact-free 40-80 % updates, per-stride gyro
de-biasing, quiet-standing anchoring, automatic tuning; :mod:`pipeline.filter_inputs`, :mod:`pipeline.tuning`), its
level then taken per cycle from the cycle-mean gravity (:func:`gravity_levelled`, :mod:`pipeline.cycle_gravity`):
the filter's own level in motion follows the accelerometer angle through the joint centres, and over a long run it
wandered by up to 6 deg per leg on the simulator (150 s runs) and trend peaks read 3-10 deg high on an independent
one. GO's zero-angle update does not apply: a running knee never straightens (minimum ~15-25 deg). Rhudy et al.
found KF and CF slightly better than their EKF (Table 2, Vicon-tuned). With these inputs and no reference tuning the
EKF came out best on the simulator (bench/accuracy.py, running, TUNE seeds 0-9 at 100 and 200 Hz: RMSE EKF 2.17, KF
2.57, CF 3.35 deg; per-stride peak LoA EKF -6.9..5.0, KF -5.5..7.5): its update ``P |a| |b| / (P |a|^2 + r)
sin(alpha_acc - x)`` bounds the pull of a large accelerometer-angle error (the sine) and weighs it by the
acceleration magnitudes. Without quiet standing in the session the EKF's level would be the joint-plane frames'
(10-30 deg off, and different at every mounting); its curve then takes GO's level per stride (:func:`go_levelled`,
reason ``go_level``), which does not depend on the mounting, with a quality below the trend threshold: a running
knee never straightens, so GO's zero leaves the absolute level unknown by 10-25 deg.

**Both**: an angle outside ``PostureParams.plausible_knee_deg`` is masked (:func:`mask_implausible`), and every
stride whose standing flexion was assumed rather than measured says so (``assumed_level``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from pipeline.cycle_gravity import cycle_knee_deg, window_knee_deg
from pipeline.estimators import get_estimator
from pipeline.estimators.cf import walking_cf
from pipeline.estimators.go import GoDiagnostics, go_relative, integrate_runs
from pipeline.estimators.kf import FilterDiagnostics
from pipeline.leg_input import EstimatorDiagnostics, LegInput
from pipeline.params import FusionParams, QualityParams
from pipeline.phases import midstance_bounds
from pipeline.posture import in_bouts, standing_mask, standing_reference
from pipeline.quality import stride_quality
from pipeline.quiet_bridge import bridged_angle, bridged_offsets, level_check, stride_check
from pipeline.signal_utils import ranges_mask, row_norm, segment_sums
from pipeline.tuning import TuningDiagnostics
from pipeline.types import AbsoluteReference


@dataclass(frozen=True)
class StrideChoice:
    """The policy's verdict on one gait-event stride."""

    estimator: str
    quality: float  # 0 (untrustworthy) .. 1 (all checks passed)
    reasons: tuple[str, ...]
    fallback: bool  # the activity's primary estimator failed here and ``estimator`` replaced it


@dataclass(frozen=True)
class PolicyResult:
    """Angle (N,) [deg], per-sample estimator names (N,) ("" where no estimate), one choice per stride of
    ``leg.events.strides``, and what anchored the level."""

    angle_deg: np.ndarray
    estimator: np.ndarray
    choices: tuple[StrideChoice, ...]
    absolute_reference: AbsoluteReference
    standing_ref_deg: float | None = None
    cf_shift_deg: float | None = None
    offset_median_deg: float | None = None
    tuning: TuningDiagnostics | None = None
    masked_implausible_samples: int = 0  # samples outside ``PostureParams.plausible_knee_deg``, set to NaN
    # the gyro-bridged level minus the strides' mid-stance level (gravity's, its neighbours' or the accelerometer's)
    # [deg] (median over strides), and whether the bridged one was taken (FusionParams.bridge_disagree_deg)
    bridge_check_deg: float | None = None
    level_bridged: bool = False
    # the same check on the CF fallback strides alone (their level follows the accelerometer in motion), and whether
    # they were moved by it; ``level_bridged`` also holds when only they were
    fallback_bridge_check_deg: float | None = None
    # walking auto: per stride the mid-stance level (stance_offsets, before any bridge; NaN without one) and the
    # quiet upright standing mask it was anchored on, which the mounting check reuses (pipeline.mounting.level_step)
    stance_levels_deg: np.ndarray | None = None
    standing: np.ndarray | None = None
    # running auto: the median shift [deg] that moved the filter's curve to the cycle-mean gravity level
    # (:func:`gravity_levelled`), None where that level was not found
    gravity_shift_deg: float | None = None


def _reference(ref: float | None) -> AbsoluteReference:
    return AbsoluteReference.NONE if ref is None else AbsoluteReference.STANDING


def _tuning(diag: EstimatorDiagnostics) -> TuningDiagnostics | None:
    return diag.tuning if isinstance(diag, FilterDiagnostics) else None


def auto(leg: LegInput) -> PolicyResult:
    """The ``auto`` policy of the leg's activity, implausible angles masked (:func:`mask_implausible`)."""
    return mask_implausible(leg, running_auto(leg) if leg.activity == "running" else walking_auto(leg))


def mask_implausible(leg: LegInput, result: PolicyResult) -> PolicyResult:
    """The result with every angle outside ``PostureParams.plausible_knee_deg`` set to NaN (no estimator label) and
    counted: an angle a knee cannot reach means a wrong level, sign or segment, so neither the sample nor the stride
    around it (:mod:`pipeline.session` reports only strides with a finite angle throughout) can be vouched for."""
    lo, hi = leg.params.posture.plausible_knee_deg
    angle = result.angle_deg
    with np.errstate(invalid="ignore"):
        bad = (angle < lo) | (angle > hi)
    n_bad = int(bad.sum())
    if not n_bad:
        return result
    angle = np.where(bad, np.nan, angle)
    labels = np.where(bad, "", result.estimator).astype(str)
    return replace(result, angle_deg=angle, estimator=labels, masked_implausible_samples=n_bad)


def _level_reasons(leg: LegInput) -> tuple[str, ...]:
    """``assumed_level`` unless the standing flexion the level rests on was measured (a calibration)."""
    return () if leg.params.posture.standing_knee_measured else ("assumed_level",)


def single_estimator(leg: LegInput, name: str) -> PolicyResult:
    """One registered estimator alone: every stride is its own, with full quality (nothing checked). Without quiet
    standing in the session an accelerometer-fused estimator's level would be the joint-plane frames' own, which
    moves with the mounting and with anything that moves the joint-centre fit (on the real biomechZoo trial 36 deg
    for a 0.05 g accelerometer bias, 22 deg for a 2 % gain error: bench.real_perturb); its curve takes GO's level
    instead (:func:`go_levelled`, reason ``go_level``), as the running policy does."""
    angle, diag = get_estimator(name)(leg)
    angle = np.asarray(angle, dtype=float)
    ref = diag.standing_ref_deg
    levelled = go_levelled(leg, angle, go_relative(leg)[0]) if ref is None and name != "go" else None
    reasons = _level_reasons(leg)
    if levelled is not None:
        angle = levelled
        reasons = ("no_absolute_reference", "go_level", *reasons)
    labels = np.where(np.isfinite(angle), name, "").astype(str)
    choice = StrideChoice(estimator=name, quality=1.0, reasons=reasons, fallback=False)
    return mask_implausible(leg, PolicyResult(
        angle_deg=angle, estimator=labels, choices=tuple(choice for _ in leg.events.strides),
        absolute_reference=_reference(ref), standing_ref_deg=None if ref is None else round(ref, 2),
        tuning=_tuning(diag)))


def running_auto(leg: LegInput) -> PolicyResult:
    """The running policy: ``RunningParams.auto_estimator`` (the EKF) on every stride. Without a standing zero its
    level would be the joint-plane frames' own (sensor->knee directions tilted 10-30 deg by the sensors' offsets
    from the segment axes), so the EKF curve is moved to GO's level instead (:func:`go_levelled`): no absolute
    reference either, but one that does not depend on where the sensors sit; the strides say so (``go_level``) and
    lose quality. Quality is capped like walking's (:func:`pipeline.quality.stride_quality`): ``assumed_level``
    without a calibration."""
    rp = leg.params.running
    name = rp.auto_estimator
    angle, diag = get_estimator(name)(leg)
    ref = diag.standing_ref_deg
    # GO's curve: the level without a standing zero, and what the filter's level is checked against per stride
    go_rel = go_relative(leg)[0] if leg.events.strides else None
    levelled = go_levelled(leg, angle, go_rel) if ref is None and go_rel is not None else None
    if levelled is not None:
        angle = levelled
    gravity_shift, check, bridged_level = None, None, False
    standing = standing_mask(leg) if ref is not None else None
    if standing is not None:
        # the filter's level in motion rests on the accelerometer angle, which the joint centres and the axes' fit
        # carry; the cycle-mean gravity needs neither (pipeline.cycle_gravity)
        angle, gravity_shift = gravity_levelled(leg, angle, standing)
    if ref is not None and standing is not None and leg.fs_hz >= rp.bridge_min_fs_hz:
        # the quiet standing around each run checks the level again (pipeline.quiet_bridge), as walking's: where
        # no whole cycle gave gravity's level, the filter's own is all there was
        fp = leg.params.fusion
        check = level_check(leg, angle, ref - leg.params.posture.standing_knee_deg, fp, standing)
        if check is not None and abs(check) > rp.bridge_disagree_deg:
            angle = angle + check
            bridged_level = True
    labels = np.where(np.isfinite(angle), name, "").astype(str)
    reasons: tuple[str, ...] = (() if ref is not None else ("no_absolute_reference",))
    reasons += (("go_level",) if levelled is not None else ()) + _level_reasons(leg)
    # the same caps as walking (pipeline.quality): a level resting on the assumed standing flexion is never vouched
    # for, whichever estimator carries the curve
    base = rp.no_reference_quality if ref is None else 1.0
    choice = StrideChoice(estimator=name, quality=min(base, stride_quality(reasons, leg.params.quality)),
                          reasons=reasons, fallback=False)
    wandering = (*reasons, "level_wander")
    wander = StrideChoice(estimator=name, quality=min(base, stride_quality(wandering, leg.params.quality)),
                          reasons=wandering, fallback=False)
    wandered = [] if go_rel is None else _wandering(go_offsets(leg, angle, go_rel), rp.level_wander_deg)
    return PolicyResult(angle_deg=angle, estimator=labels,
                        choices=tuple(wander if w else choice for w in wandered),
                        absolute_reference=_reference(ref), standing_ref_deg=None if ref is None else round(ref, 2),
                        tuning=_tuning(diag), bridge_check_deg=None if check is None else round(check, 2),
                        level_bridged=bridged_level,
                        gravity_shift_deg=None if gravity_shift is None else round(gravity_shift, 2))


def gravity_shifts(leg: LegInput, angle: np.ndarray, standing: np.ndarray, rate_dps: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per running cycle ``[start, stop)`` that gives a level from the cycle-mean gravity
    (:func:`pipeline.cycle_gravity.cycle_knee_deg`, ``FusionParams.gravity_tol_mps2``): its first sample, its stop
    and the shift [deg] that moves ``angle`` (N,) onto that level. The gravity angle at the foot strike is carried
    through the cycle by the knee rate ``rate_dps`` (N,), integrated by the trapezoid (a left sum would sit half a
    sample's turn low at the strike, where the knee flexes at 200-400 deg/s: +1 deg at 100 Hz; a cycle lies within
    one valid run, so only differences are read); the shift is the mean of that path minus ``angle`` over the cycle:
    a cycle's mean survives a low-pass filter, a single sample does not. ``standing``: quiet
    standing, whose up directions are the zero."""
    lo, hi, knee = cycle_knee_deg(leg, standing, leg.params.fusion.gravity_tol_mps2)
    if lo.size == 0:
        return lo, hi, np.zeros(0)
    path = integrate_runs(rate_dps, leg.fs_hz, leg.prep.valid & np.isfinite(rate_dps))
    d = path - angle
    ok = np.isfinite(d)
    n_ok = segment_sums(ok, lo, hi)
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = knee - path[lo] + segment_sums(np.where(ok, d, 0.0), lo, hi) / n_ok
    good = np.isfinite(shift) & (n_ok > 0)
    return lo[good], hi[good], shift[good]


def gravity_levelled(leg: LegInput, angle: np.ndarray, standing: np.ndarray) -> tuple[np.ndarray, float | None]:
    """``angle`` (N,) [deg] moved, within the running cycles, to the level of the cycle-mean gravity
    (:func:`gravity_shifts`), and the median shift [deg].

    The knee rate is that of the unfiltered signals (``leg.unfiltered``; the 7 Hz low-pass rounds the knee's turn at
    the strike, where the angle is read). The shifts are smoothed over neighbouring cycles
    (``FusionParams.offset_smooth``, as walking's levels) and interpolated between cycle centres; towards each period
    of quiet standing (``standing``) they fall to zero, where the filter's own level is the static angle. Fewer than
    ``FusionParams.gravity_min_cycles`` cycles with a level, or ``gravity_level`` off, leave ``angle`` as it is
    (shift None)."""
    fp = leg.params.fusion
    if not fp.gravity_level:
        return angle, None
    raw = leg.unfiltered
    rate_dps = leg.rate_dps if raw is None else np.rad2deg(raw.gyr_thigh_rps @ leg.axes.j1
                                                           - raw.gyr_shank_rps @ leg.axes.j2)
    lo, hi, shift = gravity_shifts(leg, angle, standing, rate_dps)
    if lo.size < fp.gravity_min_cycles:
        return angle, None
    centres = 0.5 * (lo + hi)
    shift = _running_median(shift, fp.offset_smooth)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], standing.astype(np.int8), [0])))).reshape(-1, 2)
    at = np.concatenate((centres, edges[:, 0], edges[:, 1] - 1))
    value = np.concatenate((shift, np.zeros(edges.size)))
    order = np.argsort(at, kind="stable")
    return angle + np.interp(np.arange(angle.shape[0]), at[order], value[order]), float(np.median(shift))


def _wandering(offsets: np.ndarray, limit_deg: float) -> list[bool]:
    """Per stride, whether its level against GO (:func:`go_offsets`) lies more than ``limit_deg`` from the leg's
    median (a stride without both estimates does not wander)."""
    finite = np.isfinite(offsets)
    if not finite.any():
        return [False] * offsets.size
    with np.errstate(invalid="ignore"):
        return (np.abs(offsets - np.median(offsets[finite])) > limit_deg).tolist()


def go_offsets(leg: LegInput, angle: np.ndarray, go_rel: np.ndarray) -> np.ndarray:
    """Per stride of ``leg.events.strides`` the mean of (GO - ``angle``) over it [deg] (NaN without both estimates
    in it): ``angle``'s level against GO's (``go_rel``, :func:`pipeline.estimators.go.go_relative`; Allseits et al.
    2018: zero at the knee-angle minimum before swing)."""
    arr = np.asarray(leg.events.strides, dtype=int).reshape(-1, 3)
    lo, hi = arr[:, 0], arr[:, 2] + 1
    d = go_rel - angle
    ok = np.isfinite(d)
    n_ok = segment_sums(ok, lo, hi)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n_ok > 0, segment_sums(np.where(ok, d, 0.0), lo, hi) / np.maximum(n_ok, 1), np.nan)


def go_levelled(leg: LegInput, angle: np.ndarray, go_rel: np.ndarray) -> np.ndarray | None:
    """``angle`` (N,) [deg] shifted per stride to the level of GO (:func:`go_offsets`), smoothed over neighbouring
    strides (``FusionParams.offset_smooth``) and interpolated between stride centres; held outside the strides.
    None without a stride with both estimates."""
    strides = leg.events.strides
    if not strides:
        return None
    arr = np.asarray(strides)
    lo, hi = arr[:, 0], arr[:, 2] + 1
    offs = go_offsets(leg, angle, go_rel)
    finite = np.isfinite(offs)
    if not finite.any():
        return None
    level = float(np.median(offs[finite]))
    smooth = _running_median(np.where(finite, offs, level), leg.params.fusion.offset_smooth)
    return angle + np.interp(np.arange(angle.shape[0]), 0.5 * (lo + hi - 1), smooth)


def walking_auto(leg: LegInput) -> PolicyResult:
    """The walking policy: absolute GO per stride, CF fallback (module docstring)."""
    go_rel, go_diag = go_relative(leg)
    return fuse(leg, go_rel, go_diag, walking_cf(leg))


def _running_median(x: np.ndarray, width: int) -> np.ndarray:
    if x.size == 0:
        return x
    half = width // 2
    padded = np.pad(x, half, mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1), axis=1)


def _window_gravity_offsets(leg: LegInput, go_rel: np.ndarray, standing: np.ndarray, strides: np.ndarray,
                            p: FusionParams) -> tuple[np.ndarray, np.ndarray]:
    """Per stride ``(hs, to, hs_next)`` (K, 3) the mean of (gravity knee - GO) [deg] over its mid-stance
    (``FusionParams.midstance_window``; :func:`pipeline.cycle_gravity.window_knee_deg`), and whether it has one."""
    lo, hi = midstance_bounds(strides.tolist(), p.midstance_window)
    knee = window_knee_deg(leg, standing, p.gravity_tol_mps2, strides[:, [0, 2]], lo, hi)
    d = knee - go_rel
    ok = np.isfinite(d)
    n = segment_sums(ok, lo, hi)
    with np.errstate(invalid="ignore", divide="ignore"):
        return segment_sums(np.where(ok, d, 0.0), lo, hi) / np.maximum(n, 1), n > 0


def _gravity_filled(offs: np.ndarray, shift: np.ndarray, gravity: np.ndarray, strides: np.ndarray, p: FusionParams
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per stride ``(hs, to, hs_next)`` (K, 3), its level [deg] and whether it comes from gravity: its own
    (``shift`` where ``gravity``), else, within ``FusionParams.offset_smooth`` strides of a gravity-levelled one and
    where the leg has ``gravity_min_cycles`` of them, theirs (running median over them, interpolated in time at
    the stride's middle), else its accelerometer level ``offs``. A stride with a hole has no gravity level of its own
    (the gyros cannot carry gravity through it), and a leg's level changes slowly from stride to stride; the median
    keeps one wrong gravity stride from spreading, and the reach keeps a level from travelling to another bout."""
    idx = np.flatnonzero(gravity)
    if idx.size < p.gravity_min_cycles or idx.size == gravity.size:
        return np.where(gravity, shift, offs), gravity
    mid = 0.5 * (strides[:, 0] + strides[:, 2])
    level = np.interp(mid, mid[idx], _running_median(shift[idx], p.offset_smooth))
    after = np.minimum(np.searchsorted(idx, np.arange(gravity.size)), idx.size - 1)
    reach = np.minimum(np.abs(idx[after] - np.arange(gravity.size)),
                       np.abs(idx[np.maximum(after - 1, 0)] - np.arange(gravity.size)))
    filled = ~gravity & (reach <= p.offset_smooth)
    return np.where(gravity, shift, np.where(filled, level, offs)), gravity | filled


def stance_offsets(leg: LegInput, go_rel: np.ndarray, strides: list[tuple[int, int, int]]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of (accelerometer angle - GO) [deg] over the calm mid-stance samples of each stride, and the calm-sample
    count. Mid-stance: ``FusionParams.midstance_window`` of the stride, never past toe-off (no heel-strike shock, no
    push-off). Calm: both segments' angular speed below ``FusionParams.calm_dps`` (lever-arm terms of Eq. 6 small);
    a stride with fewer than ``min_quiet_samples`` calm samples uses all of its mid-stance. The running median over
    strides (:func:`fuse`) removes outliers."""
    if not strides:
        return np.zeros(0), np.zeros(0, dtype=int)
    p = leg.params.fusion
    prep = leg.prep
    speed = np.rad2deg(np.maximum(row_norm(prep.gyr_thigh_rps), row_norm(prep.gyr_shank_rps)))
    diff = leg.acc_angle_deg - go_rel
    ok = np.isfinite(diff)
    d0 = np.where(ok, diff, 0.0)
    quiet = ok & (speed < p.calm_dps)
    lo, hi = midstance_bounds(strides, p.midstance_window)
    n_quiet = segment_sums(quiet, lo, hi)
    n_ok = segment_sums(ok, lo, hi)
    s_quiet = segment_sums(np.where(quiet, d0, 0.0), lo, hi)
    s_ok = segment_sums(d0, lo, hi)
    with np.errstate(invalid="ignore", divide="ignore"):
        offs = np.where(n_quiet >= p.min_quiet_samples, s_quiet / np.maximum(n_quiet, 1), s_ok / n_ok)
    offs[n_ok == 0] = np.nan
    return offs, n_quiet.astype(int)


@dataclass(frozen=True)
class _StrideFlags:
    """Per-stride checks of the walking policy, aligned with the strides."""

    go_complete: np.ndarray
    no_crossing: np.ndarray
    drifted: np.ndarray
    saturated: np.ndarray
    bridged: np.ndarray
    mismatch: np.ndarray


def _stride_flags(leg: LegInput, go_diag: GoDiagnostics, go_abs: np.ndarray, cf_used: np.ndarray,
                  lo: np.ndarray, hi: np.ndarray) -> _StrideFlags:
    """The checks of each stride ``[lo, hi)`` from prefix sums (no per-sample Python work)."""
    p = leg.params.fusion
    prep = leg.prep
    n_len = hi - lo
    go_complete = segment_sums(np.isfinite(go_abs), lo, hi) == n_len
    saturated = segment_sums(prep.saturated, lo, hi) > 0
    bridged = np.zeros(n_len.size, dtype=bool)
    for g0, g1 in prep.bridged_s:
        i0, i1 = np.searchsorted(prep.t_s, [g0, g1])
        bridged |= (lo <= i1) & (hi > i0)
    no_crossing, drifted = _go_failures(go_diag, p, lo, hi)
    e = go_abs - cf_used
    e_ok = np.isfinite(e)
    e0 = np.where(e_ok, e, 0.0)
    ne = np.maximum(segment_sums(e_ok, lo, hi), 1)
    mean_e = segment_sums(e0, lo, hi) / ne
    var_e = np.maximum(segment_sums(e0 * e0, lo, hi) / ne - mean_e ** 2, 0.0)
    return _StrideFlags(go_complete=go_complete, no_crossing=no_crossing, drifted=drifted, saturated=saturated,
                        bridged=bridged, mismatch=np.sqrt(var_e) > p.mismatch_deg)


def _go_failures(go_diag: GoDiagnostics, p: FusionParams, lo: np.ndarray, hi: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per stride ``[lo, hi)``: whether GO found no zero crossing in it, and whether its drift exceeded
    ``p.drift_max_deg``."""
    zi, zf, drift = go_diag.zau_idx, go_diag.zau_found, go_diag.drift_deg
    zl, zh = np.searchsorted(zi, lo), np.searchsorted(zi, hi)
    missing = np.concatenate(([0], np.cumsum(~zf)))
    no_crossing = (missing[zh] - missing[zl]) > 0
    big_drift = np.concatenate(([0], np.cumsum(np.nan_to_num(np.abs(drift)) > p.drift_max_deg))) if drift.size \
        else np.zeros(1, dtype=int)
    d_lo, d_hi = np.clip(zl - 1, 0, drift.size), np.clip(zh, 0, drift.size)
    return no_crossing, (big_drift[d_hi] - big_drift[d_lo]) > 0


def _choose(flags: _StrideFlags, k: int, absolute_ok: bool, quiet_count: int, p: FusionParams,
            q: QualityParams, level_reasons: tuple[str, ...] = (), gravity: bool = False) -> StrideChoice:
    """GO or the CF fallback for stride ``k``, its quality and reasons. ``gravity``: GO's level in the stride comes
    from the cycle-mean gravity (its own or its neighbours', :func:`_gravity_filled`), which needs no calm mid-stance
    samples (the CF's level does)."""
    failed = [reason for flag, reason in ((not flags.go_complete[k], "no_go_estimate"),
                                          (flags.no_crossing[k], "no_zero_crossing"), (flags.drifted[k], "drift"),
                                          (flags.saturated[k], "saturation")) if flag]
    use_go = not failed
    reasons: list[str] = list(level_reasons)
    if not absolute_ok:
        reasons.append("no_absolute_reference")
    elif quiet_count < p.min_quiet_samples and not (gravity and use_go):
        reasons.append("few_quiet_samples")
    reasons += failed
    if flags.bridged[k]:
        reasons.append("bridged_gap")
    if flags.mismatch[k]:
        # either estimator may be the wrong one: a CF fallback is no more vouched for than GO when they disagree
        reasons.append("go_cf_mismatch")
    if not use_go:
        reasons.append("cf_fallback")
    return StrideChoice(estimator="go" if use_go else "cf", quality=stride_quality(reasons, q),
                        reasons=tuple(reasons),
                        fallback=not use_go)


def fuse(leg: LegInput, go_rel: np.ndarray, go_diag: GoDiagnostics, cf: np.ndarray) -> PolicyResult:
    """Per-sample fused angle, per-sample estimator names and one :class:`StrideChoice` per stride of
    ``leg.events.strides``. Outside strides (standing, sitting, turning without strides) the CF estimate is used."""
    p = leg.params.fusion
    strides = leg.events.strides
    n = go_rel.shape[0]
    standing = standing_mask(leg, exclude=in_bouts(leg))
    ref = standing_reference(leg, leg.acc_angle_deg, standing=standing)
    absolute_ok = ref is not None
    # acc - ref reads 0 when standing; standing itself is standing_knee_deg of flexion
    ref_deg = ref - leg.params.posture.standing_knee_deg if ref is not None else 0.0
    offs, quiet_counts = stance_offsets(leg, go_rel + ref_deg, strides)
    stance_levels = offs
    check, bridged_level, bridged_ang = None, False, None
    arr = np.asarray(strides, dtype=int).reshape(-1, 3)
    lo, hi = arr[:, 0], arr[:, 2] + 1
    gravity = np.zeros(len(strides), dtype=bool)  # strides levelled by the cycle-mean gravity
    if absolute_ok and strides and p.gravity_level:
        # the stride's mean gravity over its mid-stance, where the stride gives it (else its neighbours'): no joint
        # centre, lever arm or soft tissue enters it (pipeline.cycle_gravity); its strides need no calm samples
        shift, gravity = _window_gravity_offsets(leg, go_rel, standing, arr, p)
        offs, gravity = _gravity_filled(offs, shift, gravity, arr, p)
    if absolute_ok and strides:
        # the level the gyros carry from the quiet standing around each walk (quiet_bridge), against the mid-stance
        # level of the strides whose GO holds (a GO that found no zero crossing or drifted has no level to check)
        bridged_ang = bridged_angle(leg, ref_deg, p, standing)
        bridged = bridged_offsets(leg, go_rel, bridged_ang, strides)
        no_crossing, drifted = _go_failures(go_diag, p, lo, hi)
        both = np.isfinite(bridged) & np.isfinite(offs) & ~no_crossing & ~drifted
        if both.sum() >= p.bridge_min_strides:
            check = float(np.median(bridged[both] - offs[both]))
            if abs(check) > p.bridge_disagree_deg:
                # strides outside the bridges move with the leg: their mid-stance level is off by the same
                offs = np.where(np.isfinite(bridged), bridged, offs + check)
                bridged_level = True
    finite = np.isfinite(offs)
    raw_level = float(np.median(offs[finite])) if finite.any() else 0.0
    if absolute_ok and finite.any():
        smooth = _running_median(np.where(finite, offs, raw_level), p.offset_smooth)
        cf_shift = -ref_deg
    else:
        smooth = np.zeros(len(strides))
        # keep CF consistent with GO's zero when there is no absolute reference
        cf_shift = -raw_level - ref_deg
    cf_used = cf + cf_shift
    angle = cf_used.copy()
    labels = np.where(np.isfinite(angle), "cf", "")
    reference = _reference(ref)
    ref_out = None if ref is None else round(ref, 2)
    if not strides:
        return PolicyResult(angle_deg=angle, estimator=labels.astype(str), choices=(), absolute_reference=reference,
                            standing_ref_deg=ref_out, cf_shift_deg=round(cf_shift, 2), standing=standing)
    centres = np.array([(a + b) / 2.0 for a, _, b in strides])
    go_abs = go_rel + np.interp(np.arange(n), centres, smooth)
    flags = _stride_flags(leg, go_diag, go_abs, cf_used, lo, hi)
    level = _level_reasons(leg)
    # a choice depends on the stride only through its flags: one per distinct combination, shared (frozen)
    keys = np.column_stack([getattr(flags, f.name) for f in fields(_StrideFlags)]
                           + [quiet_counts < p.min_quiet_samples, gravity]).tolist()
    made: dict[tuple[bool, ...], StrideChoice] = {}
    for k, key in enumerate(map(tuple, keys)):
        if key not in made:
            made[key] = _choose(flags, k, absolute_ok, int(quiet_counts[k]), p, leg.params.quality, level,
                                bool(gravity[k]))
    choices = tuple(made[key] for key in map(tuple, keys))
    use = np.array([c.estimator == "go" for c in choices])
    # GO inside the strides that kept it; extending it to the bout edges (gait initiation and termination, where
    # its drift line is extrapolated) is worse on the simulator (crouch) and mixed on the real trial
    go_mask = ranges_mask(n, lo[use], hi[use])
    cf_check = None if bridged_ang is None else stride_check(bridged_ang - cf_used, lo[~use], hi[~use],
                                                             p.bridge_min_strides)
    cf_moves = cf_check is not None and abs(cf_check) > p.bridge_disagree_deg
    if cf_moves or (cf_check is None and bridged_level):
        # the CF in a fallback stride follows the accelerometer's level in motion: checked by the bridges on its own
        # strides where they reach them, else moved with the leg's GO strides when their level was rejected;
        # outside the strides (standing, sitting) it is the static angle and stays
        angle[ranges_mask(n, lo[~use], hi[~use])] += cf_check if cf_moves else check
    if check is None and cf_check is not None:
        check = cf_check
    angle[go_mask] = go_abs[go_mask]
    labels = np.where(go_mask, "go", labels)
    labels = np.where(np.isfinite(angle), labels, "")
    return PolicyResult(angle_deg=angle, estimator=labels.astype(str), choices=choices, absolute_reference=reference,
                        standing_ref_deg=ref_out, cf_shift_deg=round(cf_shift, 2),
                        offset_median_deg=round(raw_level, 2),
                        bridge_check_deg=None if check is None else round(check, 2),
                        level_bridged=bridged_level or cf_moves,
                        fallback_bridge_check_deg=None if cf_check is None else round(cf_check, 2),
                        stance_levels_deg=stance_levels, standing=standing)
