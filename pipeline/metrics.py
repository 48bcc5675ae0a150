"""Per-stride knee metrics (heel strike to the next heel strike of the same leg), as reported by Allseits et al.
2018 (peak swing flexion, Sect. 2.4.2) and Potter et al. 2022 (range of motion per stride), plus temporal
parameters from the gait events."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipeline.params import WALKING, MetricsParams
from pipeline.types import StrideValues


def stride_values(angle_deg: np.ndarray, t_s: np.ndarray, hs: int, to: int, hs_next: int,
                  params: MetricsParams = WALKING.metrics) -> StrideValues:
    """Metrics of one stride ``[hs, hs_next]`` (sample indices) with toe-off ``to``; ``angle_deg`` (N,) must be
    finite on the stride, ``t_s`` (N,) its time stamps [s]."""
    return stride_values_many(angle_deg, t_s, [(hs, to, hs_next)], params)[0]


def stride_values_many(angle_deg: np.ndarray, t_s: np.ndarray, strides: Sequence[tuple[int, int, int]],
                       params: MetricsParams = WALKING.metrics) -> list[StrideValues]:
    """:func:`stride_values` of every stride ``(hs, to, hs_next)``, all at once: each extremum is one
    ``reduceat`` over the stride's samples (a maximum or minimum does not depend on the order it is taken in)."""
    if not len(strides):
        return []
    arr = np.asarray(strides, dtype=int).reshape(-1, 3)
    hs, to, hs_next = arr[:, 0], arr[:, 1], arr[:, 2]
    load_end = hs + np.maximum(np.round(params.loading_share * (to - hs)).astype(int), 1)
    # only the span the strides cover, plus one padding sample that keeps ``hi == len`` a valid reduceat index
    base, end = int(hs.min()), int(max(hs_next.max(), load_end.max())) + 1
    angle = np.append(np.asarray(angle_deg, dtype=float)[base:end], 0.0)
    hs, to, hs_next, load_end = hs - base, to - base, hs_next - base, load_end - base
    peak = _range_max(angle, to, hs_next + 1)
    low = _range_extreme(np.minimum, angle, hs, hs_next + 1)
    high = _range_max(angle, hs, hs_next + 1)
    stance = _range_max(angle, hs, load_end + 1)
    hs, to, hs_next = hs + base, to + base, hs_next + base
    t = np.asarray(t_s, dtype=float)
    t0, t1, tt = t[hs], t[hs_next], t[to]
    cols = (t0, t1, t1 - t0, tt, tt - t0, t1 - tt, 100.0 * (tt - t0) / (t1 - t0), peak, low, high - low, stance)
    return [StrideValues(*row) for row in zip(*(c.tolist() for c in cols), strict=True)]


def _range_max(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return _range_extreme(np.maximum, x, lo, hi)


def _range_extreme(op: np.ufunc, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``op`` (np.maximum / np.minimum) over each ``x[lo:hi]`` (``lo < hi < len(x)``: the caller pads ``x`` by one
    sample), ignoring NaN unless all are NaN. Interleaved ``reduceat`` indices reduce ``[lo_k, hi_k)`` at even
    positions."""
    idx = np.column_stack([lo, hi]).ravel()
    out = op.reduceat(x, idx)[::2]
    for k in np.flatnonzero(np.isnan(out)):  # a NaN propagates: take the NaN-aware extremum there
        seg = x[lo[k]:hi[k]]
        out[k] = np.nanmax(seg) if op is np.maximum else np.nanmin(seg)
    return out
