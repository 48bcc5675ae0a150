"""Per-stride quality: what a stride's reasons cost, and the stride-side reasons (gaps, bout edges).

A stride's quality is 1 minus the penalties of its reasons (:class:`pipeline.params.QualityParams`), floored at 0.
A reason in ``QualityParams.untrusted`` caps it below the trend threshold (``server.trends.metrics.MIN_QUALITY`` =
0.5): its peak or minimum was not measured, or it is not a gait stride. A level that rests on the assumed standing
flexion (``assumed_level``: no calibration) caps it at 0.75: such a stride may enter trends, but only a calibrated
stride scores >= 0.8, the band the robustness sweep shows to be within ~3 deg of the truth. The estimators'
reasons come from :mod:`pipeline.policy`; the data's reasons from here:

- ``bridged_gap``: the stride holds a hole filled from the neighbouring strides
  (:func:`pipeline.prepare.periodic_fill`);
- ``event_in_gap``: a heel strike or toe-off lies in such a hole (its timing is the neighbours', not measured);
- ``peak_in_gap``: the stride's swing peak or minimum of the angle lies in such a hole longer than
  ``QualityParams.filled_peak_s``, or the swing-flexion rise just before the peak does, or a cubic bridge too long
  to keep that rise (the metric itself is a model);
- ``long_gap``: the stride touches a filled hole longer than ``QualityParams.trusted_fill_s`` (half a stride: a
  whole swing or stance phase may be the neighbours');
- ``bout_edge``: the first or last stride of a bout is not steady (gait initiation and termination change stride
  time and swing speed: Jian et al. 1993, steady state within ~2 strides);
- ``turning``: the body turned by more than ``QualityParams.max_turn_deg`` over the stride (:func:`turn_reasons`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from pipeline.params import WALKING, QualityParams
from pipeline.strapdown import cycle_turn_deg
from pipeline.types import StrideMetrics


def stride_quality(reasons: Sequence[str], params: QualityParams = WALKING.quality) -> float:
    """Quality 0..1 of a stride with ``reasons`` (rounded to 3 decimals)."""
    q = max(0.0, 1.0 - sum(params.penalty(r) for r in reasons))
    if any(r in params.untrusted for r in reasons):
        q = min(q, params.untrusted_cap)
    if any(r in params.unmeasured_level for r in reasons):
        q = min(q, params.unmeasured_level_cap)
    return round(q, 3)


def _hole_mask(t_s: np.ndarray, holes: Sequence[tuple[float, float]], margin: int, lead_s: float = 0.0
               ) -> np.ndarray:
    """True for the samples of ``t_s`` in any hole ``(t_last_before, t_first_after)`` or up to ``lead_s`` [s]
    after it, widened by ``margin`` samples on either side."""
    n = t_s.shape[0]
    marks = np.zeros(n + 1, dtype=int)
    for g0, g1 in holes:
        i0 = max(int(np.searchsorted(t_s, g0, side="right")) - margin, 0)
        i1 = min(int(np.searchsorted(t_s, g1 + lead_s, side="left")) + margin, n)
        if i1 > i0:
            marks[i0] += 1
            marks[i1] -= 1
    return np.cumsum(marks)[:-1] > 0


def gap_reasons(t_s: np.ndarray, filled_s: Sequence[tuple[float, float]], angle_deg: np.ndarray,
                strides: Sequence[tuple[int, int, int]], margin: int = 1,
                bridged_s: Sequence[tuple[float, float]] = (), peak_lead_s: float = 0.0,
                short_fill_s: float = 0.0, trusted_fill_s: float = float("inf")) -> list[tuple[str, ...]]:
    """The gap reasons of each stride ``(hs, to, hs_next)`` (sample indices of ``t_s``) against the filled holes
    ``filled_s`` (``(t_last_before, t_first_after)`` [s]). ``angle_deg`` (N,): finite on the strides. An event or
    extremum within ``margin`` samples of a hole counts as inside (the fill is matched to its edge samples).

    The swing peak is also ``peak_in_gap`` when it lies up to ``peak_lead_s`` [s] after a hole (a modelled part of
    the swing-flexion rise sets the peak's level) and for the holes ``bridged_s`` as well (bridged by the cubic
    but too long for it to keep the rise; their other reasons come from the policy). Filled holes up to
    ``short_fill_s`` [s] long leave the peak and minimum measured; a stride touching one longer than
    ``trusted_fill_s`` [s] is ``long_gap``. See ``QualityParams.peak_lead_s``, ``QualityParams.filled_peak_s``,
    ``QualityParams.bridged_peak_s`` and ``QualityParams.trusted_fill_s``."""
    if not (filled_s or bridged_s) or not strides:
        return [() for _ in strides]
    inside = _hole_mask(t_s, filled_s, margin)
    long_fills = [(g0, g1) for g0, g1 in filled_s if g1 - g0 > short_fill_s]
    in_long = _hole_mask(t_s, long_fills, margin)
    near = _hole_mask(t_s, [*long_fills, *bridged_s], margin, peak_lead_s)
    cum = np.concatenate(([0], np.cumsum(inside)))
    cum_long = np.concatenate(([0], np.cumsum(_hole_mask(t_s, [(g0, g1) for g0, g1 in filled_s
                                                                if g1 - g0 > trusted_fill_s], margin))))
    cum_touched = np.concatenate(([0], np.cumsum(near | inside)))
    out: list[tuple[str, ...]] = []
    for a, t, b in strides:
        if cum_touched[b + 1] == cum_touched[a]:
            out.append(())
            continue
        reasons = []
        if cum[b + 1] != cum[a]:
            reasons.append("bridged_gap")
            if inside[a] or inside[t] or inside[b]:
                reasons.append("event_in_gap")
        peak = t + int(np.argmax(angle_deg[t:b + 1]))
        low = a + int(np.argmin(angle_deg[a:b + 1]))
        if near[peak] or in_long[low]:
            reasons.append("peak_in_gap")
        if cum_long[b + 1] != cum_long[a]:
            reasons.append("long_gap")
        out.append(tuple(reasons))
    return out


def edge_reasons(strides: Sequence[tuple[int, int, int]], bout_of_stride: Sequence[int], swing_peak_dps: np.ndarray,
                 duration_tol: float = 0.1, peak_tol: float = 0.15) -> list[tuple[str, ...]]:
    """``bout_edge`` for the first and last stride of each bout whose duration or shank swing peak
    (``swing_peak_dps``, one per stride) is off the bout's median by more than ``duration_tol`` / ``peak_tol``."""
    out: list[tuple[str, ...]] = [() for _ in strides]
    if not strides:
        return out
    bouts = np.asarray(bout_of_stride)
    dur = np.array([b - a for a, _, b in strides], dtype=float)
    peak = np.asarray(swing_peak_dps, dtype=float)
    for bout in np.unique(bouts):
        idx = np.flatnonzero(bouts == bout)
        if idx.size < 3:
            continue
        inner = idx[1:-1]
        d_med, p_med = float(np.median(dur[inner])), float(np.median(peak[inner]))
        for k in (idx[0], idx[-1]):
            if abs(dur[k] - d_med) > duration_tol * d_med or abs(peak[k] - p_med) > peak_tol * abs(p_med):
                out[k] = ("bout_edge",)
    return out


def with_reason(strides: Sequence[StrideMetrics], reason: str, params: QualityParams = WALKING.quality
                ) -> list[StrideMetrics]:
    """``strides`` with ``reason`` among their quality reasons and their quality capped by it (those that have it
    already unchanged)."""
    return [st if reason in st.quality_reasons else dataclasses.replace(
        st, quality_reasons=(*st.quality_reasons, reason),
        quality=min(st.quality, stride_quality((*st.quality_reasons, reason), params))) for st in strides]


def turn_reasons(gyr_thigh_rps: np.ndarray, gyr_shank_rps: np.ndarray, fs_hz: float,
                 strides: Sequence[tuple[int, int, int]], max_turn_deg: float) -> list[tuple[str, ...]]:
    """``turning`` for each stride ``(hs, to, hs_next)`` (sample indices of the (N, 3) gyros [rad/s] at ``fs_hz``)
    over which both segments turned by more than ``max_turn_deg`` [deg] from one heel strike to the next
    (:func:`pipeline.strapdown.cycle_turn_deg`): both, so that one sensor's artefact does not take a stride out."""
    if not strides:
        return []
    arr = np.asarray(strides, dtype=int)
    a, b = arr[:, 0], arr[:, 2]
    turn = np.minimum(cycle_turn_deg(np.nan_to_num(gyr_thigh_rps), fs_hz, a, b),
                      cycle_turn_deg(np.nan_to_num(gyr_shank_rps), fs_hz, a, b))
    return [("turning",) if x > max_turn_deg else () for x in turn]
