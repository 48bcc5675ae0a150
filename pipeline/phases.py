"""Gait events from the shank's sagittal angular velocity (positive = shank swinging forward, see
:mod:`pipeline.axes`).

Events follow Allseits et al. 2018 (Sect. 2.2 and Fig. 4: mid-swing peak, heel strike, mid-stance, toe-off from the
shank angular velocity) with the Salarian-style rules they build on: the mid-swing (MS) peak is the maximum of a
positive swing lobe; toe-off (TO) is the minimum just before the lobe starts, heel strike (HS) follows the end of
the lobe (the shank stops swinging forward). Mid-stance (MSt) is taken half-way between HS and the next TO (the
Allseits zero-angle update only needs a point after loading response and before push-off).

Timing against the force plate of the Tan et al. 2022 treadmill steps (real data, ``bench/real_data.py``): the shank
minimum precedes toe-off by ~40 ms (``to_delay_s`` added) and heel strike comes ~10-30 ms after the smoothed zero
crossing. When the shank accelerometer is given, HS is the heel-strike impact: the largest jump of the specific force
within ``impact_window_s`` of the zero crossing (if it stands out of the window), otherwise the zero crossing +
``hs_delay_s`` (:class:`pipeline.params.PhaseParams`).

Robustness to standing, sitting, sit-to-stand, turns and slow walking: lobes must exceed an adaptive height
threshold, consecutive MS peaks must be separated by a clearly negative (stance) region, and only bouts of at least
``PhaseParams.min_bout_peaks`` peaks with consistent periods produce strides. No stride spans a masked sample or
ends next to one (``PhaseParams.gap_guard_s``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from pipeline.params import WALKING, PhaseParams
from pipeline.signal_utils import lowpass, row_norm


@dataclass(frozen=True)
class GaitEvents:
    """Per swing lobe (aligned arrays, index -1 when not found): ``ms`` mid-swing peak, ``to`` toe-off before it,
    ``hs`` heel strike after it, ``mst`` mid-stance after ``hs`` (before the next lobe's ``to``), ``bout`` the walking
    bout id (-1: not part of a consistent bout). ``strides`` are ``(hs_start, to, hs_end)`` sample triples."""

    ms: np.ndarray
    to: np.ndarray
    hs: np.ndarray
    mst: np.ndarray
    bout: np.ndarray
    strides: list[tuple[int, int, int]] = field(default_factory=list)


def shank_sagittal_dps(gyr_dps: np.ndarray) -> np.ndarray:
    """Shank-only sagittal rate for short windows without a thigh: principal rotation axis (McGrath et al. 2018),
    signed so the largest excursions (mid-swing) are positive. Full sessions use the fitted knee axis instead."""
    g = np.asarray(gyr_dps, dtype=float)
    _, _, vt = np.linalg.svd(g, full_matrices=False)
    w = g @ vt[0]
    if -np.percentile(w, 0.5) > np.percentile(w, 99.5):
        w = -w
    return w


def _swing_lobes(ws: np.ndarray, min_height: float) -> list[tuple[int, int, int]]:
    """``(start, peak, stop)`` of each positive lobe of the smoothed rate reaching ``min_height`` (start/stop may be
    the signal edges). Vectorised: standing noise makes thousands of tiny lobes."""
    pos = ws > 0
    if not pos.any():
        return []
    edges = np.diff(np.concatenate(([0], pos.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    heights = np.maximum.reduceat(ws, starts)
    keep = heights >= min_height
    # each lobe's peak = its first sample equal to the lobe maximum (what argmax per lobe returns), found for all
    # lobes at once: the positive samples are exactly the lobes, in order
    pos_idx = np.flatnonzero(pos)
    at_max = pos_idx[ws[pos_idx] == np.repeat(heights, stops - starts)]
    peaks = at_max[np.searchsorted(at_max, starts[keep])]
    return list(zip(starts[keep].tolist(), peaks.tolist(), stops[keep].tolist(), strict=True))


def _merge_lobes(ws: np.ndarray, lobes: list[tuple[int, int, int]], fs_hz: float, stance_neg_dps: float
                 ) -> list[tuple[int, int, int]]:
    """Merge lobes separated only by a shallow, short dip (noise inside one swing) - keep the higher peak.

    A merged lobe ends where its last lobe ends, so the dip before each lobe is the one after its predecessor
    whether or not that was merged: all dips are tested at once (standing noise makes thousands of lobes)."""
    if len(lobes) < 2:
        return list(lobes)
    arr = np.asarray(lobes)
    after, before = arr[:-1, 2], arr[1:, 0]  # each dip [after, before): never empty between two positive runs
    dip_min = np.minimum.reduceat(ws, np.column_stack([after, before]).ravel())[::2]
    joins = np.where(before > after, dip_min > -stance_neg_dps, True) & (before - after < 0.15 * fs_hz)
    merged = [lobes[0]]
    for lobe, join in zip(lobes[1:], joins.tolist(), strict=True):
        if join:
            a, p, _ = merged[-1]
            merged[-1] = (a, p if ws[p] >= ws[lobe[1]] else lobe[1], lobe[2])
        else:
            merged.append(lobe)
    return merged


def _heel_strikes(zc: np.ndarray, n: int, fs_hz: float, jerk: np.ndarray | None, p: PhaseParams) -> np.ndarray:
    """HS after the end of each swing lobe (indices ``zc``): the impact onset if one stands out of the window
    (largest jump > ``impact_prominence`` x the window's median jump), else the zero crossing + ``hs_delay_s``.
    Vectorised over lobes: one (lobes x window) matrix."""
    fallback = np.minimum(zc + int(round(p.hs_delay_s * fs_hz)), n - 1)
    if jerk is None or zc.size == 0:
        return fallback
    off = np.arange(int(round(p.impact_window_s[0] * fs_hz)), int(round(p.impact_window_s[1] * fs_hz)) + 1)
    idx = zc[:, None] + off[None, :]
    inside = (idx >= 1) & (idx < n)
    win = np.where(inside, jerk[np.clip(idx, 0, n - 1)], 0.0)
    k = np.argmax(win, axis=1)
    peak = win[np.arange(zc.size), k]
    med = np.median(np.where(inside, win, np.nan), axis=1) if inside.all() else np.nanmedian(
        np.where(inside, win, np.nan), axis=1)
    stands_out = peak > p.impact_prominence * np.maximum(np.nan_to_num(med), 1e-9)
    # onset: the last sample before the first jump of at least half the largest
    before_peak = np.arange(off.size)[None, :] <= k[:, None]
    first = np.argmax((win >= 0.5 * peak[:, None]) & before_peak, axis=1)
    onset = idx[np.arange(zc.size), first] - 1
    return np.where(stands_out & (onset >= 0), onset, fallback)


def detect_gait_events(shank_sag_dps: np.ndarray, fs_hz: float, valid: np.ndarray | None = None,
                       min_bout_peaks: int | None = None, shank_acc_mps2: np.ndarray | None = None,
                       params: PhaseParams = WALKING.phases) -> GaitEvents:
    """Mid-swing, toe-off, heel-strike and mid-stance indices from a shank sagittal angular velocity (N,) [deg/s].

    ``valid`` (default all True) marks usable samples: events are not searched inside masked samples (they are
    treated as zero rate), and no stride spans one. ``min_bout_peaks=1`` accepts isolated swings (short windows;
    default ``params.min_bout_peaks``). ``shank_acc_mps2`` (N, 3), optional: refines heel strike to the impact.
    """
    p = params
    w = np.asarray(shank_sag_dps, dtype=float)
    n = w.shape[0]
    valid = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    empty = np.zeros(0, dtype=int)
    if n < 5:
        return GaitEvents(empty, empty, empty, empty, empty)
    w0 = np.where(valid, np.nan_to_num(w), 0.0)
    ws = lowpass(w0, p.lobe_cutoff_hz, fs_hz)
    we = lowpass(w0, p.event_cutoff_hz, fs_hz)
    ws[~valid] = 0.0
    lobes = _swing_peaks(ws, fs_hz, p)
    if not lobes:
        return GaitEvents(empty, empty, empty, empty, empty)
    ms_a = np.array([pk for _, pk, _ in lobes], dtype=int)
    starts = np.array([a for a, _, _ in lobes], dtype=int)
    to_a = _toe_offs(we, starts, ms_a, fs_hz, p)
    ends = np.array([b for _, _, b in lobes], dtype=int)
    jerk = _jerk(shank_acc_mps2, valid)
    hs_a = np.where(ends < n, _heel_strikes(np.minimum(ends, n - 1), n, fs_hz, jerk, p), -1)
    bout = _bouts(ms_a, ws, valid, fs_hz, p.min_bout_peaks if min_bout_peaks is None else min_bout_peaks, p)
    mst = np.full(ms_a.size, -1)
    for k in range(ms_a.size - 1):
        if hs_a[k] >= 0 and to_a[k + 1] > hs_a[k]:
            mst[k] = (hs_a[k] + to_a[k + 1]) // 2
    strides = _strides(ms_a, to_a, hs_a, bout, valid, fs_hz, p)
    return GaitEvents(ms=ms_a, to=to_a, hs=hs_a, mst=mst, bout=bout, strides=strides)


def _swing_peaks(ws: np.ndarray, fs_hz: float, p: PhaseParams) -> list[tuple[int, int, int]]:
    """Swing lobes of the smoothed rate ``ws``: lobes reaching ``min_peak_dps`` that are swings among the session's
    (``rel_peak`` of the upper quartile of its lobes) or swings among their neighbours (``rel_peak_local`` of the
    largest of the ``rel_window_lobes`` lobes on either side that lie within ``max_period_s`` of it).

    Why the upper quartile, not the median: in mid-stance the tibia rolls forward over the foot, a positive lobe of
    its own (80-100 deg/s in fast walking on an independent simulator, a third of the swing's), one per stride at
    most, so up to half of the lobes may be stance lobes and their median falls between the two kinds; the upper
    quartile is a swing peak either way. Why the neighbours too: the swing peak grows with walking speed (~150
    deg/s in a rehabilitation shuffle, ~450 in brisk walking) and a session mixes both, so a shuffle is a third of
    the session's swings and would fail their rule. Among its neighbours it passes: consecutive swings of steady
    gait are alike (stride-to-stride variability of a few %), so the local rule asks for more (nearly as large as
    the largest lobe within a stride of it, not a third of the typical one) and still rejects the tibia's roll and
    the small lobes of the trailing leg in a step-up, which lie next to lobes twice their height. The local rule only
    adds lobes, so a session of one pace finds what it found with the session's rule alone."""
    lobes = _merge_lobes(ws, _swing_lobes(ws, 0.5 * p.min_peak_dps), fs_hz, p.stance_neg_dps)
    if not lobes:
        return []
    arr = np.asarray(lobes)
    heights = ws[arr[:, 1]]
    big = np.flatnonzero(heights >= p.min_peak_dps)
    if big.size == 0:
        return []
    session = p.rel_peak * float(np.percentile(heights[big], 75))
    k = p.rel_window_lobes
    h = np.pad(heights[big], k, constant_values=np.nan)
    t = np.pad(arr[big, 1].astype(float), k, constant_values=np.nan)
    h_win, t_win = sliding_window_view(h, 2 * k + 1), sliding_window_view(t, 2 * k + 1)
    near = np.abs(t_win - t_win[:, k:k + 1]) <= p.max_period_s * fs_hz  # NaN padding compares False
    local = p.rel_peak_local * np.where(near, h_win, 0.0).max(axis=1)
    keep = heights[big] >= np.minimum(session, local)
    return [lobes[i] for i in big[keep].tolist()]


def _toe_offs(we: np.ndarray, starts: np.ndarray, ms_a: np.ndarray, fs_hz: float, p: PhaseParams) -> np.ndarray:
    """Toe-off before each lobe: minimum of ``we`` over ``[a - search, a]`` before each lobe start ``a`` plus
    ``to_delay_s``, all lobes at once; -1 for a lobe starting at the signal edge. The +inf padding before the
    signal start is never the minimum, so each window's argmin (first minimum) is the clipped window's: the same
    index as a per-lobe argmin."""
    search = max(int(round(p.search_s * fs_hz)), 2)
    to_delay = int(round(p.to_delay_s * fs_hz))
    padded = np.concatenate((np.full(search, np.inf), we))
    first = starts - search + np.argmin(sliding_window_view(padded, search + 1)[starts], axis=1)
    return np.where(starts > 0, np.minimum(first + to_delay, ms_a - 1), -1).astype(int)


def _jerk(shank_acc_mps2: np.ndarray | None, valid: np.ndarray) -> np.ndarray | None:
    """Per-sample jump of the shank specific force [m/s^2] (0 where masked), or None without an accelerometer."""
    if shank_acc_mps2 is None:
        return None
    acc = np.asarray(shank_acc_mps2, dtype=float)
    jerk = np.concatenate(([0.0], row_norm(np.diff(acc, axis=0))))
    jerk[~valid | ~np.isfinite(jerk)] = 0.0
    return jerk


def _bouts(ms: np.ndarray, ws: np.ndarray, valid: np.ndarray, fs_hz: float, min_peaks: int, p: PhaseParams
           ) -> np.ndarray:
    """Bout id per MS peak: chains of peaks with plausible, consistent periods, a real stance dip between
    consecutive peaks and no masked sample in between; chains shorter than ``min_peaks`` get -1, unless a masked
    gap ends them (then two peaks, one stride, suffice)."""
    bout = np.full(ms.size, -1)
    if ms.size == 0:
        return bout
    period = np.diff(ms) / fs_hz
    link = (period >= p.min_period_s) & (period <= p.max_period_s)
    inv_cum = np.concatenate(([0], np.cumsum(~valid)))
    # minimum of ws between consecutive peaks, all at once (peaks are increasing; the last entry is unused)
    dip = np.minimum.reduceat(ws, ms)[:-1]
    masked = inv_cum[ms[1:]] != inv_cum[ms[:-1]]
    link &= (dip < -p.stance_neg_dps) & ~masked
    # period consistency: compare each link with the median of its linked neighbourhood
    if period.size >= 3:
        padded = np.pad(np.where(link, period, np.nan), 2, constant_values=np.nan)
        windows = np.lib.stride_tricks.sliding_window_view(padded, 5)
        with np.errstate(all="ignore"):
            local = np.nanmedian(np.where(np.isnan(windows).all(axis=1, keepdims=True), 1.0, windows), axis=1)
        link &= np.abs(period - local) <= p.period_tol * local
    # a chain cut by missing data is not an isolated step: the strides beyond the hole were walked, not observed
    cut_before = np.concatenate(([False], masked))
    cut_after = np.concatenate((masked, [False]))
    chain_id = 0
    start = 0
    for k in range(ms.size):
        end_of_chain = k == ms.size - 1 or not link[k]
        if end_of_chain:
            need = min(min_peaks, 2) if cut_before[start] or cut_after[k] else min_peaks
            if k - start + 1 >= need:
                bout[start:k + 1] = chain_id
                chain_id += 1
            start = k + 1
    return bout


def _strides(ms: np.ndarray, to: np.ndarray, hs: np.ndarray, bout: np.ndarray,
             valid: np.ndarray, fs_hz: float, p: PhaseParams) -> list[tuple[int, int, int]]:
    """Strides HS(k) -> TO(k+1) -> HS(k+1) for consecutive peaks of one bout, plausible stance share, no masked
    sample within ``gap_guard_s`` of the stride."""
    inv_cum = np.concatenate(([0], np.cumsum(~valid)))
    n = valid.shape[0]
    guard = int(round(p.gap_guard_s * fs_hz))
    out = []
    for k in range(ms.size - 1):
        if bout[k] < 0 or bout[k] != bout[k + 1]:
            continue
        a, t, b = int(hs[k]), int(to[k + 1]), int(hs[k + 1])
        if a < 0 or t < 0 or b < 0 or not (a < t < ms[k + 1] < b):
            continue
        stance_pct = 100.0 * (t - a) / (b - a)
        if not (p.stance_pct_range[0] <= stance_pct <= p.stance_pct_range[1]):
            continue
        if inv_cum[min(b + guard, n - 1) + 1] != inv_cum[max(a - guard, 0)]:
            continue
        out.append((a, t, b))
    return out


def midstance_bounds(strides: list[tuple[int, int, int]], window: tuple[float, float]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Per stride ``(hs, to, hs_next)`` the half-open sample range ``[lo, hi)`` of its mid-stance: the share
    ``window`` of the stride from heel strike, never past toe-off, at least one sample
    (``pipeline.params.FusionParams.midstance_window``)."""
    arr = np.asarray(strides, dtype=int).reshape(-1, 3)
    length = arr[:, 2] - arr[:, 0]
    w0, w1 = window
    lo = arr[:, 0] + np.round(w0 * length).astype(int)
    hi = np.maximum(np.minimum(arr[:, 0] + np.round(w1 * length).astype(int), arr[:, 1]) + 1, lo + 1)
    return lo, hi
