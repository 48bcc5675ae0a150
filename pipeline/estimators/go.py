"""Gyroscope-only (GO) knee angle of Allseits et al., Sensors 2018 (Sect. 2.2, Fig. 3): low-pass the knee angular
velocity g1.j1 - g2.j2 (Seel Eq. 4 integrand), integrate it, and apply one zero-angle update (ZAU) per stride.

The ZAU sits at the knee-angle MINIMUM just before swing flexion: after mid-stance and before toe-off, where the
flexion velocity crosses from negative (extension) to positive (flexion) - checked against the kinematics, not the
paper's wording (their sign convention differs). Between consecutive updates the accumulated drift is distributed
linearly (the integral is made to return to zero at each update), so the angle is continuous.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.leg_input import EstimatorDiagnostics, LegInput
from pipeline.signal_utils import lowpass_runs, true_runs


@dataclass(frozen=True, kw_only=True)
class GoDiagnostics(EstimatorDiagnostics):
    """The zero-angle updates of one leg (aligned arrays, one entry per update). GO has no absolute reference
    (``standing_ref_deg`` stays None): its zero is the straight knee assumed before swing."""

    zau_idx: np.ndarray  # sample index of each update
    zau_bout: np.ndarray  # bout id of each update
    zau_found: np.ndarray  # True where a negative->positive rate crossing was found
    drift_deg: np.ndarray  # drift removed between an update and the previous one of its bout, NaN across bouts


def integrate_runs(rate_dps: np.ndarray, fs_hz: float, valid: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral (N,) [deg] of the rate (N,) [deg/s], restarted at zero on every valid run;
    NaN elsewhere."""
    out = np.full(rate_dps.shape[0], np.nan)
    for a, b in true_runs(valid):
        r = rate_dps[a:b]
        out[a:b] = np.concatenate(([0.0], np.cumsum(0.5 * (r[1:] + r[:-1])) / fs_hz))
    return out


def zau_points(rate_f: np.ndarray, integral: np.ndarray, leg: LegInput) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One ZAU per swing lobe that belongs to a bout: ``(index, bout_id, found_crossing)``.

    Search window: from the preceding mid-stance (or ``GoParams.first_zau_lookback_s`` before toe-off for a bout's
    first swing) to ``zau_after_to_s`` after toe-off. Among the negative->positive crossings of the filtered rate in
    the window the one with the lowest integral wins; without any crossing the window's integral minimum is used
    (flagged).
    """
    ev = leg.events
    fs = leg.fs_hz
    p = leg.params.go
    empty = np.zeros(0, dtype=int)
    # crossings and non-finite samples located once for the whole signal, then looked up per window (the same
    # crossings a per-window scan finds: a crossing at i needs samples i-1 and i, both inside [lo, hi)); all
    # windows at once
    cross_all = np.flatnonzero((rate_f[:-1] < 0) & (rate_f[1:] >= 0)) + 1
    bad_cum = np.concatenate(([0], np.cumsum(~np.isfinite(integral))))
    bout, to, ms, mst = (np.asarray(a, dtype=int) for a in (ev.bout, ev.to, ev.ms, ev.mst))
    k = np.flatnonzero((bout >= 0) & (to >= 0))
    if k.size == 0:
        return empty, empty, np.zeros(0, dtype=bool)
    hi = np.minimum(to[k] + int(p.zau_after_to_s * fs) + 1, ms[k])
    prev = np.maximum(k - 1, 0)
    prev_ok = (k > 0) & (bout[prev] == bout[k]) & (mst[prev] >= 0)
    back = np.maximum((to[k] - p.first_zau_lookback_s * fs).astype(int), 0)  # int(): truncation, as per window
    lo = np.where(prev_ok, mst[prev], back)
    use = (hi - lo >= 3) & (bad_cum[np.clip(hi, 0, None)] == bad_cum[np.clip(lo, 0, None)])
    k, lo, hi = k[use], lo[use], hi[use]
    c0 = np.searchsorted(cross_all, lo + 1)
    c1 = np.maximum(np.searchsorted(cross_all, hi - 1, side="right"), c0)
    best = np.empty(k.size, dtype=int)
    found = c1 > c0
    # the crossing with the lowest integral per window (first of equals, as argmin): sort by window, value, position
    cnt = c1 - c0
    win = np.repeat(np.arange(k.size), cnt)
    pos = cross_all[c0[win] + np.arange(win.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)] if win.size else empty
    order = np.lexsort((pos, integral[pos], win))
    first = np.concatenate(([True], win[order][1:] != win[order][:-1])) if order.size else np.zeros(0, dtype=bool)
    best[win[order][first]] = pos[order][first]
    for j in np.flatnonzero(~found):  # no crossing: the window's integral minimum (rare)
        best[j] = lo[j] + int(np.argmin(integral[lo[j]:hi[j]]))
    return best, bout[k], found


def go_relative(leg: LegInput) -> tuple[np.ndarray, GoDiagnostics]:
    """GO angle (N,) [deg] with the per-stride zero (Allseits Sect. 2.2), NaN outside the span of each bout's
    updates, and the updates (:class:`GoDiagnostics`)."""
    valid = leg.prep.valid
    rate_f = lowpass_runs(np.nan_to_num(leg.rate_dps), valid, leg.params.go.cutoff_hz, leg.fs_hz)
    integral = integrate_runs(np.nan_to_num(rate_f), leg.fs_hz, valid)
    zi, zb, zf = zau_points(rate_f, integral, leg)
    out = np.full(integral.shape[0], np.nan)
    ev = leg.events
    for b in np.unique(zb):
        pts = zi[zb == b]
        if pts.size == 0:
            continue
        lobes = np.flatnonzero(ev.bout == b)
        hs_last = ev.hs[lobes[-1]] if ev.hs[lobes[-1]] >= 0 else pts[-1]
        lo, hi = int(min(pts[0], ev.hs[lobes[0]] if ev.hs[lobes[0]] >= 0 else pts[0])), int(max(pts[-1], hs_last))
        seg = np.arange(lo, hi + 1)
        out[seg] = integral[seg] - np.interp(seg, pts, integral[pts])
    drift = np.diff(integral[zi]) if zi.size > 1 else np.zeros(0)
    same_bout = np.diff(zb) == 0 if zb.size > 1 else np.zeros(0, dtype=bool)
    return out, GoDiagnostics(zau_idx=zi, zau_bout=zb, zau_found=zf, drift_deg=np.where(same_bout, drift, np.nan))
