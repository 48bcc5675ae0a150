"""Small signal helpers shared by the pipeline modules (zero-phase filters, run-length segments)."""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, sosfiltfilt


def lowpass(x: np.ndarray, cutoff_hz: float, fs_hz: float, order: int = 2) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (Allseits et al. 2018, Sect. 2.4.1 filter the knee angular
    velocity with a low-order Butterworth; zero phase keeps event timing unbiased). Short or NaN-free inputs only."""
    x = np.asarray(x, dtype=float)
    if cutoff_hz >= 0.5 * fs_hz or x.shape[0] < 3 * (order + 1) * 2:
        return x.copy()
    sos = butter(order, cutoff_hz / (0.5 * fs_hz), output="sos")
    padlen = min(x.shape[0] - 1, 3 * (2 * len(sos) + 1))
    return sosfiltfilt(sos, x, axis=0, padlen=padlen)


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges ``[start, stop)`` of the runs of True in a boolean array."""
    m = np.concatenate(([False], np.asarray(mask, dtype=bool), [False]))
    d = np.diff(m.astype(np.int8))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def lowpass_runs(x: np.ndarray, valid: np.ndarray, cutoff_hz: float, fs_hz: float, order: int = 2) -> np.ndarray:
    """:func:`lowpass` applied separately to each valid run, so filters never smear across masked gaps.

    Invalid samples come back as NaN."""
    out = np.full(np.shape(x), np.nan)
    for a, b in true_runs(valid):
        out[a:b] = lowpass(x[a:b], cutoff_hz, fs_hz, order)
    return out
