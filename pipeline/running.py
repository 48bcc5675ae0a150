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
  run on the gyroscope alone there).

Pure functions over arrays (sample indices on the leg's uniform grid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt

from pipeline.signal_utils import true_runs

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
    return np.linalg.norm(np.asarray(acc_mps2, dtype=float).reshape(-1, 3), axis=1)


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
