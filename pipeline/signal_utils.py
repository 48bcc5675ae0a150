"""Small signal helpers shared by the pipeline modules (zero-phase filters, run-length segments)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
from scipy.signal import butter, sosfilt_zi, sosfiltfilt

from pipeline import kernels
from pipeline.kernels import filtfilt_columns


@lru_cache(maxsize=64)
def _butter_sos(order: int, cutoff_hz: float, fs_hz: float) -> np.ndarray:
    return butter(order, cutoff_hz / (0.5 * fs_hz), output="sos")


@lru_cache(maxsize=64)
def _sos_zi(order: int, cutoff_hz: float, fs_hz: float) -> np.ndarray:
    """Steady-state initial conditions of :func:`_butter_sos`'s sections, as ``sosfiltfilt`` computes them."""
    return sosfilt_zi(_butter_sos(order, cutoff_hz, fs_hz))


def lowpass(x: np.ndarray, cutoff_hz: float, fs_hz: float, order: int = 2) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (Allseits et al. 2018, Sect. 2.4.1 filter the knee angular
    velocity with a low-order Butterworth; zero phase keeps event timing unbiased). NaN-free input."""
    x = np.asarray(x, dtype=float)
    if cutoff_hz >= 0.5 * fs_hz or x.shape[0] < 3 * (order + 1) * 2:
        return x.copy()
    sos = _butter_sos(order, float(cutoff_hz), float(fs_hz))
    padlen = min(x.shape[0] - 1, 3 * (2 * len(sos) + 1))
    if filtfilt_columns is None or x.ndim > 2:
        return sosfiltfilt(sos, x, axis=0, padlen=padlen)
    cols = x.reshape(x.shape[0], -1)
    out = np.empty(cols.shape)
    filtfilt_columns(sos, _sos_zi(order, float(cutoff_hz), float(fs_hz)), cols, int(padlen), out)
    return out.reshape(x.shape)


def run_bounds(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Starts and stops (int arrays) of the half-open runs ``[start, stop)`` of True in a boolean array."""
    m = np.concatenate(([False], np.asarray(mask, dtype=bool), [False]))
    d = np.diff(m.astype(np.int8))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index ranges ``[start, stop)`` of the runs of True in a boolean array."""
    starts, stops = run_bounds(mask)
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def long_runs(mask: np.ndarray, min_len: float) -> np.ndarray:
    """``mask`` without its runs of True shorter than ``min_len`` samples. Vectorised: a still or standing mask
    has hundreds of runs, too many for a loop over them."""
    starts, stops = run_bounds(mask)
    keep = stops - starts >= min_len
    # the kept runs are disjoint and never touch (a False lies between two runs), so no index is set twice
    delta = np.zeros(mask.shape[0] + 1, dtype=np.int8)
    delta[starts[keep]] = 1
    delta[stops[keep]] = -1
    return np.cumsum(delta[:-1]) > 0


def away_from_holes(valid: np.ndarray, margin: int) -> np.ndarray:
    """(N,) bool: the valid samples with no invalid one within ``margin`` samples (beyond the ends counts as
    valid)."""
    return ~np.convolve(~np.asarray(valid, dtype=bool), np.ones(2 * margin + 1), mode="same").astype(bool)


def fill_invalid(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Invalid samples replaced by linear interpolation between the valid ones (constant at the ends)."""
    x = np.asarray(x, dtype=float)
    ok = np.asarray(valid, dtype=bool)
    fin = np.isfinite(x)
    # row-wise all() over (N, 3) is slow; the usual all-finite case needs no per-row test
    if not fin.all():
        ok = ok & (fin if x.ndim == 1 else fin.all(axis=1))
    return _fill_invalid_finite(x, ok)


def _fill_invalid_finite(x: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """:func:`fill_invalid` once the non-finite samples are in ``~ok``."""
    if ok.all():
        return x.copy()  # every sample finite: what np.nan_to_num would return, without its four searches
    if not ok.any():
        return np.nan_to_num(x)
    # only the invalid samples are interpolated: np.interp returns a node's own value exactly, so the valid ones
    # would come back unchanged anyway (same result as interpolating every sample, far fewer points). An invalid
    # sample lies between the last valid one before its run and the first one after it, so those are the only nodes
    # needed: interpolating on them brackets every invalid sample by the same two nodes, the same values
    bad = ~ok
    at = np.flatnonzero(bad)
    xp = np.unique(np.concatenate((np.flatnonzero(ok[:-1] & bad[1:]), np.flatnonzero(bad[:-1] & ok[1:]) + 1)))
    out = x.copy()
    if x.ndim == 1:
        out[bad] = np.interp(at, xp, x[xp])
        return out
    good = x[xp]
    for k in range(x.shape[1]):
        out[at, k] = np.interp(at, xp, good[:, k])  # the same samples as out[bad, k], by index: faster
    return out


def lowpass_runs(x: np.ndarray, valid: np.ndarray, cutoff_hz: float, fs_hz: float, order: int = 2) -> np.ndarray:
    """:func:`lowpass` over the whole signal with masked samples bridged by straight lines (one filter call however
    many gaps; the filter's short impulse response keeps the bridge's influence within a few samples of the gap).
    Invalid samples come back as NaN."""
    out = lowpass(fill_invalid(x, valid), cutoff_hz, fs_hz, order)
    out[~np.asarray(valid, dtype=bool)] = np.nan
    return out


def lowpass_runs_many(xs: Sequence[np.ndarray], valid: np.ndarray, cutoff_hz: float, fs_hz: float,
                      order: int = 2) -> list[np.ndarray]:
    """:func:`lowpass_runs` of several (N, k) signals sharing one mask, as ONE filter call on the stacked columns
    (the filter runs column by column, so each result is bit-identical to its own call, with a fraction of the
    per-call overhead). Falls back to separate calls when some input is non-finite, since the bridged samples then
    differ per signal."""
    xs = [np.asarray(x, dtype=float) for x in xs]
    block = np.hstack([x.reshape(x.shape[0], -1) for x in xs])
    if not np.isfinite(block).all():
        return [lowpass_runs(x, valid, cutoff_hz, fs_hz, order) for x in xs]
    out = lowpass_runs(block, valid, cutoff_hz, fs_hz, order)
    res, c = [], 0
    for x in xs:
        w = 1 if x.ndim == 1 else x.shape[1]
        # contiguous copies: strided views could take other (differently rounding) BLAS paths downstream
        res.append(np.ascontiguousarray(out[:, c] if x.ndim == 1 else out[:, c:c + w]))
        c += w
    return res


def lowpass_runs_zeroed(xs: Sequence[np.ndarray], valid: np.ndarray, cutoff_hz: float, fs_hz: float,
                        order: int = 2) -> list[np.ndarray]:
    """``np.nan_to_num`` of each :func:`lowpass_runs_many` output (masked samples 0, NaN-free), for the fits: the
    masked samples are zeroed directly instead of being set to NaN and then searched for NaN and infinities (four
    passes over each output). The filter runs column by column, so filtering each signal on its own gives the
    stacked call's values without stacking the inputs and splitting the outputs. Filtering finite input gives
    finite output, so the values are the same; should a filter ever overflow, the general path decides."""
    xs = [np.asarray(x, dtype=float) for x in xs]
    ok = np.asarray(valid, dtype=bool)
    if all(np.isfinite(x).all() for x in xs):
        res = []
        for x in xs:
            out = lowpass(_fill_invalid_finite(x, ok), cutoff_hz, fs_hz, order)  # finite: ok is the mask as is
            out[~ok] = 0.0
            res.append(np.ascontiguousarray(out))
        if all(np.isfinite(r).all() for r in res):
            return res
    return [np.nan_to_num(x) for x in lowpass_runs_many(xs, valid, cutoff_hz, fs_hz, order)]


def ranges_mask(n: int, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """(n,) bool: True inside any of the half-open ranges ``[starts[k], stops[k])`` (they may overlap; ``stops`` at
    most ``n``), by one difference array instead of a loop over ranges."""
    delta = np.zeros(n + 1, dtype=int)
    np.add.at(delta, starts, 1)
    np.add.at(delta, stops, -1)
    return np.cumsum(delta)[:-1] > 0


def segment_sums(x: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Sum of ``x[a:b]`` for each (non-overlapping or not) half-open range, via a prefix sum."""
    c = np.concatenate(([0.0], np.cumsum(x, dtype=float)))
    return c[stops] - c[starts]


def slower_than(gyr_rps: np.ndarray, limit_dps: float) -> np.ndarray:
    """(N,) bool: the angular rate (N, 3) [rad/s] below ``limit_dps`` [deg/s] in magnitude (the stillness test of
    :mod:`pipeline.posture` and :mod:`pipeline.rest_offset`)."""
    return np.einsum("ij,ij->i", gyr_rps, gyr_rps) < math.radians(limit_dps) ** 2


def row_norm(x: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of an (N, 3) array. Bit-identical to ``np.linalg.norm(x, axis=1)`` (whose
    reduction over a length-3 axis adds the squares in the same left-to-right order) and about five times faster."""
    x = np.asarray(x, dtype=float)
    if kernels.row_norm is not None and x.ndim == 2 and x.shape[1] == 3:
        out = np.empty(x.shape[0])
        kernels.row_norm(x, out)
        return out
    x0, x1, x2 = x[:, 0], x[:, 1], x[:, 2]
    return np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` for an (N, 3) array and a 3-vector (or another (N, 3) array): the same three products and
    differences (``a1 b2 - a2 b1``, ...), so bit-identical, without np.cross's dtype casts and axis handling (which
    cost more than the arithmetic at these sizes)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if kernels.cross_rows is not None and a.ndim == 2 and a.shape[1] == 3 and b.shape in ((3,), a.shape):
        out = np.empty((a.shape[0], 3))
        kernels.cross_rows(a, b.reshape(-1, 3), out)
        return out
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty((a.shape[0], 3))
    out[:, 0] = a1 * b2 - a2 * b1
    out[:, 1] = a2 * b0 - a0 * b2
    out[:, 2] = a0 * b1 - a1 * b0
    return out


def merged_intervals(intervals: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """``intervals`` ``(start, end)`` in order, overlapping or touching ones joined."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(intervals):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
