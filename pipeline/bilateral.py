"""Gait alternates the legs: a stride of one leg holds the other leg's swing in its stance.

In walking and running the legs move in anti-phase: the contralateral mid-swing falls about half a cycle from the
ipsilateral one (double support then single support, Perry and Burnfield 2010, Ch. 1; in running the flight phases
keep the half-cycle offset, Novacheck 1998). Two-footed jumps, squats, sit-to-stand and stepping up with both feet
move both shanks together, so their "strides" have the other leg's swing at the same phase or none at all. A stride
is kept when some mid-swing of the other leg within half a stride of it lies at least ``min_phase`` cycles
(circularly) from its own mid-swing; it cannot be judged (and is kept) where the other leg has no data.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MIN_PHASE = 0.25
"""Least circular distance [cycles] between the two legs' mid-swings: gait ~0.5; both legs together ~0; a quarter
cycle is the midpoint, far from the 0.4-0.6 of asymmetric (hemiparetic) gait."""


def alternation(strides_s: np.ndarray | Sequence[tuple[float, float, float]], other_swings_s: np.ndarray,
                other_gaps_s: Sequence[tuple[float, float]], min_phase: float = MIN_PHASE) -> np.ndarray:
    """Per stride ``(t_start, t_own_mid_swing, t_end)`` [s] (rows of ``strides_s``), whether it alternates with the
    other leg: 1 when some mid-swing of the other leg (``other_swings_s``, sorted [s]) within half a stride of it
    lies in anti-phase, 0 when none does, -1 when the other leg shows no swing there and has a data gap in the
    stride (nothing to judge). All strides at once: one (strides x candidate swings) matrix."""
    spans = np.asarray(strides_s, dtype=float).reshape(-1, 3)
    swings = np.asarray(other_swings_s, dtype=float)
    t0, ms, t1 = spans[:, 0], spans[:, 1], spans[:, 2]
    period = t1 - t0
    lo = np.searchsorted(swings, t0 - 0.5 * period)
    hi = np.searchsorted(swings, t1 + 0.5 * period)
    out = np.zeros(spans.shape[0], dtype=np.int8)
    width = int((hi - lo).max(initial=0))
    if width:
        k = lo[:, None] + np.arange(width)
        c = swings[np.minimum(k, swings.size - 1)]
        d = np.abs(((c - ms[:, None]) / period[:, None] + 0.5) % 1.0 - 0.5)
        out[((k < hi[:, None]) & (d >= min_phase)).any(axis=1)] = 1
    if other_gaps_s:
        gapped = np.zeros(spans.shape[0], dtype=bool)
        for g0, g1 in other_gaps_s:
            gapped |= (g0 < t1) & (g1 > t0)
        out[(hi == lo) & gapped] = -1
    return out


def alternates(stride_s: tuple[float, float, float], other_swings_s: np.ndarray,
               other_gaps_s: Sequence[tuple[float, float]], min_phase: float = MIN_PHASE) -> bool | None:
    """:func:`alternation` of one stride: True, False, or None (nothing to judge)."""
    v = int(alternation([stride_s], other_swings_s, other_gaps_s, min_phase)[0])
    return None if v < 0 else bool(v)


def non_alternating(strides_s: Sequence[tuple[float, float, float]] | np.ndarray, other_swings_s: np.ndarray,
                    other_gaps_s: Sequence[tuple[float, float]], min_phase: float = MIN_PHASE) -> list[int]:
    """Indices of the strides that are not gait by :func:`alternation` (judged ones only)."""
    swings = np.sort(np.asarray(other_swings_s, dtype=float))
    return np.flatnonzero(alternation(strides_s, swings, other_gaps_s, min_phase) == 0).tolist()


def mid_swings_s(own_swings_s: np.ndarray, t_toe_off_s: np.ndarray, t_end_s: np.ndarray) -> np.ndarray:
    """Each stride's own mid-swing time [s]: the first of ``own_swings_s`` (sorted [s]) between its toe-off and its
    end, else the middle of that swing interval."""
    own = np.asarray(own_swings_s, dtype=float)
    to, end = np.asarray(t_toe_off_s, dtype=float), np.asarray(t_end_s, dtype=float)
    mid = 0.5 * (to + end)
    if own.size == 0:
        return mid
    k = np.searchsorted(own, to)
    first = own[np.minimum(k, own.size - 1)]
    return np.where((k < own.size) & (first <= end), first, mid)


@dataclass(frozen=True)
class OtherLeg:
    """What the alternation check needs of the contralateral leg: its mid-swing times (sorted) and data gaps [s]; and
    for :mod:`pipeline.worn`, those of its swings that could be walking (its thigh near upright), None when that
    leg has no gait strides to tell upright from."""

    swings_s: np.ndarray
    gaps_s: tuple[tuple[float, float], ...] = ()
    walking_swings_s: np.ndarray | None = None


def stride_spans_s(t_s: np.ndarray, strides: Sequence[tuple[int, int, int]], ms: np.ndarray
                   ) -> list[tuple[float, float, float]]:
    """``(t_start, t_own_mid_swing, t_end)`` [s] of each stride ``(hs, to, hs_next)`` (sample indices of ``t_s``):
    the first mid-swing peak (``ms``, sample indices) between toe-off and the stride's end, else the middle of
    that swing interval."""
    return [tuple(r) for r in _spans(t_s, strides, ms).tolist()]


def _spans(t_s: np.ndarray, strides: Sequence[tuple[int, int, int]], ms: np.ndarray) -> np.ndarray:
    """:func:`stride_spans_s` as an (M, 3) array."""
    arr = np.asarray(strides, dtype=int).reshape(-1, 3)
    own = np.sort(np.asarray(ms, dtype=int))
    own = own[own >= 0]
    t = np.asarray(t_s, dtype=float)
    # t_s increases strictly, so comparing sample indices and comparing their times is the same
    return np.column_stack([t[arr[:, 0]], mid_swings_s(t[own], t[arr[:, 1]], t[arr[:, 2]]), t[arr[:, 2]]])


def gait_strides(t_s: np.ndarray, strides: Sequence[tuple[int, int, int]], ms: np.ndarray,
                 other: OtherLeg | None, min_phase: float = MIN_PHASE) -> list[tuple[int, int, int]]:
    """The strides that are gait by the other leg's swings (:func:`alternation` not 0): the ones allowed to decide
    anything about the leg (the thigh axis's sign, the joint-centre fit). Strides the other leg cannot judge (its
    data gap) and those of a leg alone (``other`` None) are kept: nothing says they are not gait."""
    if other is None or not strides:
        return list(strides)
    swings = np.sort(np.asarray(other.swings_s, dtype=float))
    keep = alternation(_spans(t_s, strides, ms), swings, other.gaps_s, min_phase) != 0
    return [s for s, k in zip(strides, keep.tolist(), strict=True) if k]
