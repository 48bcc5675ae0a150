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


def alternates(stride_s: tuple[float, float, float], other_swings_s: np.ndarray,
               other_gaps_s: Sequence[tuple[float, float]], min_phase: float = MIN_PHASE) -> bool | None:
    """Whether one stride ``(t_start, t_own_mid_swing, t_end)`` [s] alternates with the other leg: some mid-swing
    of the other leg (``other_swings_s``, sorted [s]) within half a stride of it lies in anti-phase. None when the
    other leg shows no swing there and has a data gap in the stride (nothing to judge)."""
    t0, ms, t1 = stride_s
    period = t1 - t0
    lo, hi = np.searchsorted(other_swings_s, [t0 - 0.5 * period, t1 + 0.5 * period])
    c = other_swings_s[lo:hi]
    if c.size == 0:
        return None if any(g0 < t1 and g1 > t0 for g0, g1 in other_gaps_s) else False
    d = np.abs(((c - ms) / period + 0.5) % 1.0 - 0.5)
    return bool(np.any(d >= min_phase))


def non_alternating(strides_s: Sequence[tuple[float, float, float]], other_swings_s: np.ndarray,
                    other_gaps_s: Sequence[tuple[float, float]], min_phase: float = MIN_PHASE) -> list[int]:
    """Indices of the strides that are not gait by :func:`alternates` (judged ones only)."""
    swings = np.sort(np.asarray(other_swings_s, dtype=float))
    return [k for k, s in enumerate(strides_s) if alternates(s, swings, other_gaps_s, min_phase) is False]


@dataclass(frozen=True)
class OtherLeg:
    """What the alternation check needs of the contralateral leg: its mid-swing times (sorted) and data gaps [s]."""

    swings_s: np.ndarray
    gaps_s: tuple[tuple[float, float], ...] = ()


def stride_spans_s(t_s: np.ndarray, strides: Sequence[tuple[int, int, int]], ms: np.ndarray
                   ) -> list[tuple[float, float, float]]:
    """``(t_start, t_own_mid_swing, t_end)`` [s] of each stride ``(hs, to, hs_next)`` (sample indices of ``t_s``):
    the first mid-swing peak (``ms``, sample indices) between toe-off and the stride's end, else the middle of
    that swing interval."""
    own = np.sort(np.asarray(ms, dtype=int))
    own = own[own >= 0]
    spans = []
    for a, t, b in strides:
        k = int(np.searchsorted(own, t))
        m = float(t_s[own[k]]) if k < own.size and own[k] <= b else 0.5 * (float(t_s[t]) + float(t_s[b]))
        spans.append((float(t_s[a]), m, float(t_s[b])))
    return spans


def gait_strides(t_s: np.ndarray, strides: Sequence[tuple[int, int, int]], ms: np.ndarray,
                 other: OtherLeg | None, min_phase: float = MIN_PHASE) -> list[tuple[int, int, int]]:
    """The strides that are gait by the other leg's swings (:func:`alternates` True): the ones allowed to decide
    anything about the leg (the thigh axis's sign, the joint-centre fit). Strides the other leg cannot judge (its
    data gap) and those of a leg alone (``other`` None) are kept: nothing says they are not gait."""
    if other is None:
        return list(strides)
    swings = np.sort(np.asarray(other.swings_s, dtype=float))
    return [s for s, span in zip(strides, stride_spans_s(t_s, strides, ms), strict=True)
            if alternates(span, swings, other.gaps_s, min_phase) is not False]
