"""Small signal helpers shared by the pipeline modules (zero-phase filters, run-length segments)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.signal import butter, sosfiltfilt


@lru_cache(maxsize=64)
def _butter_sos(order: int, cutoff_hz: float, fs_hz: float) -> np.ndarray:
    return butter(order, cutoff_hz / (0.5 * fs_hz), output="sos")


def lowpass(x: np.ndarray, cutoff_hz: float, fs_hz: float, order: int = 2) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (Allseits et al. 2018, Sect. 2.4.1 filter the knee angular
    velocity with a low-order Butterworth; zero phase keeps event timing unbiased). NaN-free input."""
    x = np.asarray(x, dtype=float)
    if cutoff_hz >= 0.5 * fs_hz or x.shape[0] < 3 * (order + 1) * 2:
        return x.copy()
    sos = _butter_sos(order, float(cutoff_hz), float(fs_hz))
    padlen = min(x.shape[0] - 1, 3 * (2 * len(sos) + 1))
    return sosfiltfilt(sos, x, axis=0, padlen=padlen)


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges ``[start, stop)`` of the runs of True in a boolean array."""
    m = np.concatenate(([False], np.asarray(mask, dtype=bool), [False]))
    d = np.diff(m.astype(np.int8))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def fill_invalid(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Invalid samples replaced by linear interpolation between the valid ones (constant at the ends)."""
    x = np.asarray(x, dtype=float)
    ok = np.asarray(valid, dtype=bool) & (np.isfinite(x) if x.ndim == 1 else np.isfinite(x).all(axis=1))
    if ok.all() or not ok.any():
        return np.nan_to_num(x)
    idx = np.arange(x.shape[0])
    if x.ndim == 1:
        return np.interp(idx, idx[ok], x[ok])
    return np.column_stack([np.interp(idx, idx[ok], x[ok, k]) for k in range(x.shape[1])])


def lowpass_runs(x: np.ndarray, valid: np.ndarray, cutoff_hz: float, fs_hz: float, order: int = 2) -> np.ndarray:
    """:func:`lowpass` over the whole signal with masked samples bridged by straight lines (one filter call however
    many gaps; the filter's short impulse response keeps the bridge's influence within a few samples of the gap).
    Invalid samples come back as NaN."""
    out = lowpass(fill_invalid(x, valid), cutoff_hz, fs_hz, order)
    out[~np.asarray(valid, dtype=bool)] = np.nan
    return out
