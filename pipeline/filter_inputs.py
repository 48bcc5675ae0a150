"""The inputs the KF, EKF and running CF share (Rhudy et al. 2024, Sect. 2.3-2.4, and what the paper got from
Vicon): the knee rate de-biased per stride, where the accelerometer may update the state, how much it is trusted,
and the valid runs the filters restart on.

Gait is periodic: over one stride the knee returns to its angle, so a stride's mean rate is the gyroscope bias (plus
the small stride-to-stride change of the angle). The filters' random-walk model assumes zero-mean gyro errors; a
bias would otherwise leave a steady offset of ``bias * tau`` (several degrees at 1 deg/s).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.axes import ANGULAR_ACCELERATION_HALF_WIDTH
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, FilterInputParams
from pipeline.signal_utils import away_from_holes, true_runs


def stride_bias_dps(rate_dps: np.ndarray, strides: list[tuple[int, int]],
                    params: FilterInputParams = WALKING.filter_inputs) -> np.ndarray | None:
    """Gyroscope bias (N,) [deg/s] of the knee rate ``rate_dps`` (N,) per sample: ``integral(rate) / duration`` of
    each stride ``(start, stop)``. Strides further than ``bias_outlier_mads`` robust SDs from the session median
    (gait initiation and termination, where the knee does change its angle over the stride) are dropped; the rest
    are smoothed by a running median over ``bias_smooth_strides`` strides and interpolated, held constant beyond the
    first and last. None without strides."""
    vals, centres = [], []
    for a, b in strides:
        r = rate_dps[a:b + 1]
        if b - a < 2 or not np.isfinite(r).all():
            continue
        vals.append(float(np.trapezoid(r) / (b - a)))
        centres.append(0.5 * (a + b))
    if not vals:
        return None
    v, c = np.asarray(vals), np.asarray(centres)
    med = float(np.median(v))
    spread = max(params.bias_outlier_mads * 1.4826 * float(np.median(np.abs(v - med))), params.bias_min_spread_dps)
    keep = np.abs(v - med) <= spread
    v, c = v[keep], c[keep]
    half = params.bias_smooth_strides // 2
    padded = np.pad(v, half, constant_values=np.nan)
    sm = np.nanmedian(np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1), axis=1)
    return np.interp(np.arange(rate_dps.shape[0]), c, sm)


def debiased_rate(leg: LegInput) -> np.ndarray:
    """The leg's knee rate (N,) [deg/s] minus its per-stride bias (:func:`stride_bias_dps`)."""
    rate = np.asarray(leg.rate_dps, dtype=float)
    bias = stride_bias_dps(rate, leg.filter_strides, leg.params.filter_inputs)
    return rate if bias is None else rate - bias


def update_mask(leg: LegInput) -> np.ndarray:
    """(N,) bool, where the accelerometer may update the filters: valid samples with a finite accelerometer angle,
    restricted by the leg's ``acc_update_mask`` when it has one (running: 40-80 % of each cycle and quiet periods,
    never at an impact). Never within the reach of Seel's Eq. 1 (``pipeline.axes.ANGULAR_ACCELERATION_HALF_WIDTH``
    samples) of a masked gap: the lever-arm term (Seel Eq. 6)
    differentiates the gyro across the hole there, whose zeroed samples make the angular acceleration and so the
    accelerometer angle anything (an EKF update with such a sample once threw a restarted filter 180 deg off)."""
    mask = away_from_holes(leg.prep.valid, ANGULAR_ACCELERATION_HALF_WIDTH) & np.isfinite(leg.acc_angle_deg)
    extra = leg.acc_update_mask
    return mask & np.asarray(extra, dtype=bool) if extra is not None else mask


def r_scale(leg: LegInput, quiet: np.ndarray) -> np.ndarray:
    """(N,) multiplier of R: ``quiet_r_scale`` on ``quiet`` samples (the accelerometer angle then sees gravity
    only and is accurate to a degree or two), 1 elsewhere."""
    return np.where(quiet, leg.params.kf.quiet_r_scale, 1.0)


def run_per_segment(leg: LegInput, fn: Callable[[int, int], np.ndarray], usable: np.ndarray,
                    restart_ok: np.ndarray | None = None) -> np.ndarray:
    """``fn(a, b)`` on each valid run ``[a, b)`` of the leg, NaN elsewhere. ``usable`` (N,) bool: where the
    accelerometer may update the filter (:func:`update_mask`); a filter starts from its first usable samples
    (:func:`pipeline.estimators.kf.start_from_measurement`), so a run without any is left NaN: it has no level.
    ``restart_ok`` (N,) bool, None for everywhere: the samples after a fill at which a restart may be made.

    The filters restart after a masked gap, and after a hole filled from the neighbouring strides
    (``PreparedLeg.filled_s``): a filter integrates the fill's rate like a measured one, and a neighbouring stride's
    integral misses the lost one's by several degrees, which a recursive filter carries forward over the following
    strides until its accelerometer updates wear it off (walking's GO restarts every stride and never carries it).
    Inside the fill the filter's angle is moved linearly onto the restarted filter's first value, as a drift between
    two anchors. A fill is restarted after only when the pieces on both sides of it hold usable samples (running
    updates in 40-80 % of each cycle only, and the measured islands between lossy stretches are short); else the
    filter carries on through it.

    Measured on running with bursty loss (tune seeds 0-9, 128 Hz, 20-sample packets): peak LoA at 3 / 5 / 10 %
    loss -8.2 .. 8.0 / -10.8 .. 10.8 / -10.2 .. 10.1 deg carried through the fills, -4.2 .. 3.9 / -5.1 .. 4.3 /
    -5.2 .. 4.1 restarted (-4.2 .. 4.0 without loss)."""
    ok = leg.prep.valid & np.isfinite(leg.rate_dps)
    measured = leg.prep.measured()
    out = np.full(ok.shape[0], np.nan)
    n_usable = np.concatenate(([0], np.cumsum(usable)))  # usable samples in [x, y): n_usable[y] - n_usable[x]
    for a, b in true_runs(ok):
        if b - a < 2 or n_usable[b] == n_usable[a]:
            continue
        m = measured[a:b]
        # a piece may restart at the first measured sample after each fill
        cands = [k for k in (a + 1 + np.flatnonzero(m[1:] & ~m[:-1])).tolist()
                 if k <= b - 2 and (restart_ok is None or restart_ok[k])]
        restarts: list[int] = []
        start = a
        for k, nxt in zip(cands, [*cands[1:], b][:len(cands)], strict=True):
            if n_usable[k] > n_usable[start] and n_usable[nxt] > n_usable[k]:
                restarts.append(k)
                start = k
        bounds = [a, *restarts, b]
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            out[s:e] = fn(s, e)
        for k1 in restarts:
            # the fill ends the piece before k1: ramp its angle onto k1's restarted value
            k0 = k1 - 1
            while k0 > a and not measured[k0]:
                k0 -= 1
            if not (np.isfinite(out[k0]) and np.isfinite(out[k1])):
                continue
            prev = out[k1 - 1] + (out[k1 - 1] - out[k1 - 2]) if k1 - 2 >= k0 else out[k1 - 1]
            u = (np.arange(k0 + 1, k1) - k0) / (k1 - k0)
            out[k0 + 1:k1] += u * (out[k1] - prev)
    return out
