"""Sensors that are not on the leg: turned unlike a knee, or resting in a posture nobody walks in while the other
leg walks.

A knee angle from two sensors is only a knee angle while both are strapped to the leg. Taken off and left on a
table (a strap that chafes, a charger, a shower), they keep recording: still, gravity only, in whatever orientation
they lie. The posture module (:mod:`pipeline.posture`) reads that as a rest, and the trace showed the table's
"angle" (on a sixth independent simulator and ours, 20-110 deg RMSE against the knee the person walked on); the
removal itself, seconds of turning unlike any knee, entered the session's hinge fit and moved the axes of the whole
leg (ours: the same leg's strides up to 6 deg off before the removal). No paper gives the rules below.

Either physical test marks a stretch:

* **handled** (:func:`handled_spans_s`): a knee is a hinge, so the two segments' angular velocities off the knee
  axis have equal magnitudes (Seel et al. 2014, Eq. 2: ``|g1 x j1| = |g2 x j2|``). Taking one sensor off while the
  other stays still breaks that by most of the rate: the RMS residual over ``handled_window_s`` above
  ``handled_ratio`` of the faster segment's RMS rate (itself above ``handled_min_dps``) for at least
  ``handled_min_s`` (the figures behind the thresholds: :class:`pipeline.params.WornParams`), after which a segment
  lies otherwise against gravity than before (``handled_turned_deg``: a removal lays the sensor down; a pivot turn
  on one foot breaks the hinge by the tibia's turn against the femur and leaves both as they were), outside the
  leg's walking bouts (a hinge broken while walking is a sensor turned on the limb: :mod:`pipeline.mounting`). The
  stretch runs from there to the leg's next walking bout (sensors back on) or the end. A sensor turned about the
  knee axis while the other is still looks like a knee flexing and is not caught.
* **resting while the other leg walks** (:func:`_resting_spans_s`): nobody walks on one leg while the other sits
  or lies still, nor with a thigh or shank that does not move. A run of at least ``min_rest_s`` in which this leg
  rests (:func:`pipeline.posture.quiet_mask`, outside its own walking bouts) and is not standing upright
  (:func:`pipeline.posture.standing_mask`), or one of its segments alone is still off the upright or within the
  leg's own walking bouts (:func:`pipeline.posture.quiet_segments`, :func:`pipeline.posture.upright_segments`: a
  thigh sensor fallen off while the shank walks on), while the other leg's shank swings at least ``min_swings``
  times with its thigh near upright (:attr:`pipeline.bilateral.OtherLeg.walking_swings_s`: a walk; all its swings
  when it has no gait strides to learn its upright from). Standing on this leg while the other one swings, or
  sitting or lying while the other one's thigh swings far from upright (one-legged exercises: seated knee
  extensions; lying ones whose thigh stays beyond ``PostureParams.upright_deg`` from upright), is a posture a body
  holds and does not count. The stretch runs on to the leg's
  first swing after the rest (sensors back on), by at most ``reach_s``.

Either stretch reaches back to the last moment the leg was surely on the body, quiet upright standing, a swing in a
walking bout or the end of a stride (the removal's turning makes no whole stride), by at most ``reach_s``. The leg
shows nothing inside its stretches (:func:`blanked`); where the sensors were handled, or a segment lay still while
its leg walked (fallen off), the session processes the pieces on either side apart (:mod:`pipeline.session`,
:func:`pieces_s`, :func:`joined`), each learning its own knee axes and level (the sensors may have gone back on
otherwise, and neither the handling nor the still segment is knee motion for the hinge fit; a piece without a gait
stride shows nothing). A rest alone neither splits nor cuts the leg's data: on an independent
simulator, cutting the still leg's rests of one-legged exercises out cost its strides 0.2-0.6 deg of mean accuracy
(the rests' orientations inform the accelerometer offsets, :mod:`pipeline.rest_offset`). The other leg's strides
there are still judged against this leg as recorded, so a lying or seated one-legged exercise cannot become gait.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy.ndimage import uniform_filter1d

from pipeline.bilateral import OtherLeg
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, WornParams
from pipeline.posture import in_bouts, leg_quiet, quiet_segments, standing_mask, upright_segments
from pipeline.prepare import PreparedLeg
from pipeline.signal_utils import long_runs, merged_intervals, ranges_mask, true_runs
from pipeline.types import LegResult


def not_worn_spans_s(leg: LegInput, other: OtherLeg | None, params: WornParams = WALKING.worn
                     ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """Time spans ``(t0, t1)`` [s, the leg's clock] in which the leg's sensors were not on the leg (module
    docstring: handled, or resting while the other leg walks), in order and disjoint; and those of them that hold a
    stretch of handling (the sensors may have gone back on otherwise)."""
    resting, fallen = _resting_spans_s(leg, other, params)
    # a segment still while its leg walks fell off or slipped: its data would move the whole leg's axes, as handling's
    handled = [*handled_spans_s(leg, params), *fallen]
    spans = merged_intervals([*handled, *resting])
    return spans, [sp for sp in spans if any(h0 < sp[1] and h1 > sp[0] for h0, h1 in handled)]


def handled_spans_s(leg: LegInput, params: WornParams = WALKING.worn) -> list[tuple[float, float]]:
    """Spans from each stretch in which the two sensors turned unlike a hinge (module docstring) to the leg's next
    walking bout; stretches within the leg's walking bouts or one of its strides do not count (it was walking: a
    hinge broken there is a sensor turned on the limb, :mod:`pipeline.mounting`)."""
    prep = leg.prep
    t_s, fs = prep.t_s, prep.fs_hz
    j1, j2 = leg.axes.j1, leg.axes.j2
    g1 = np.where(prep.valid[:, None], prep.gyr_thigh_rps, 0.0)
    g2 = np.where(prep.valid[:, None], prep.gyr_shank_rps, 0.0)
    off_axis = np.linalg.norm(np.cross(g1, j1), axis=1) - np.linalg.norm(np.cross(g2, j2), axis=1)
    rate = np.maximum(np.einsum("ij,ij->i", g1, g1), np.einsum("ij,ij->i", g2, g2))
    size = max(int(round(params.handled_window_s * fs)), 1)
    resid_ms = uniform_filter1d(off_axis**2, size, mode="nearest")
    rate_ms = uniform_filter1d(rate, size, mode="nearest")
    unlike = (rate_ms > np.radians(params.handled_min_dps) ** 2) & (resid_ms > params.handled_ratio**2 * rate_ms)
    # within walking bouts the leg was walking: a hinge broken there is a mounting change (pipeline.mounting)
    bouts = in_bouts(leg)
    unlike = long_runs(unlike & prep.valid & ~bouts, params.handled_min_s * fs)
    if not unlike.any():
        return []
    strides = np.array([(t_s[a], t_s[c]) for a, _, c in leg.events.strides]).reshape(-1, 2)
    bout_starts = t_s[np.flatnonzero(np.diff(bouts.astype(np.int8)) == 1) + 1]
    settled = _settled_s(leg, standing_mask(leg), params)
    spans = []
    for a, b in true_runs(unlike):
        t0, t1 = float(t_s[a]), float(t_s[b - 1])
        if ((strides[:, 0] <= t0) & (strides[:, 1] >= t1)).any() or _a_turn_of_the_body(prep, a, b, params):
            continue
        later = bout_starts[bout_starts > t1]  # the next walk, whole: sensors back on
        spans.append((_back_to(settled, t0, float(t_s[0]), params), float(later[0]) if later.size else float(t_s[-1])))
    return spans


def _a_turn_of_the_body(prep: PreparedLeg, a: int, b: int, params: WornParams) -> bool:
    """Whether samples ``a:b`` leave both segments lying against gravity over the second after them as over the
    second before (within ``handled_turned_deg``): the body turned, no sensor was handled. A pivot on one foot turns
    the shank about the vertical, the tibia against the femur by up to 20 deg, and breaks the hinge as much as a
    removal; a removal lays the sensor down, putting it back stands it up again."""
    n = int(round(prep.fs_hz))
    ok = prep.valid
    before, after = slice(max(a - n, 0), a), slice(b, min(b + n, prep.n))
    if not ok[before].any() or not ok[after].any():
        return False
    cos_max = np.cos(np.radians(params.handled_turned_deg))
    for acc in (prep.acc_thigh_mps2, prep.acc_shank_mps2):
        u, v = acc[before][ok[before]].mean(axis=0), acc[after][ok[after]].mean(axis=0)
        if u @ v < cos_max * np.linalg.norm(u) * np.linalg.norm(v):
            return False
    return True


def _resting_spans_s(leg: LegInput, other: OtherLeg | None, params: WornParams
                     ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """Spans in which the leg rested in a posture other than standing while the other leg walked (module
    docstring), and those of a segment alone still within the leg's own walking (fallen off); empty without the
    other leg's swings."""
    swings_s = None if other is None else other.swings_s if other.walking_swings_s is None else other.walking_swings_s
    if swings_s is None or swings_s.size < params.min_swings:
        return [], []
    prep = leg.prep
    t_s = prep.t_s
    still = quiet_segments(prep, leg.params.posture)
    if not _runs_while_swinging(still[0] | still[1], t_s, swings_s, params):
        return [], []  # no segment rests long enough while the other leg swings (every plain session)
    quiet = leg_quiet(leg)
    bouts = in_bouts(leg)
    standing = standing_mask(leg, quiet, bouts)
    rest = quiet & ~bouts & ~standing
    # one segment alone still off the upright, or still at all within the leg's own walking (a walking thigh turns
    # every stride): a thigh sensor fallen off while the shank walks on (its strides also move the segment's upright)
    upright = upright_segments(leg) or (np.zeros(prep.n, dtype=bool),) * 2
    for seg_still, up in zip(still, upright, strict=True):
        rest |= seg_still & (bouts | ~up)
    ev = leg.events
    own = np.sort(t_s[ev.ms[ev.ms >= 0]])
    settled = _settled_s(leg, standing, params)

    def spans_of(mask: np.ndarray) -> list[tuple[float, float]]:
        out = []
        for t0, t1 in _runs_while_swinging(mask, t_s, swings_s, params):
            m = int(np.searchsorted(own, t1, side="right"))
            out.append((_back_to(settled, t0, float(t_s[0]), params),
                        min(float(own[m]) if m < own.size else float(t_s[-1]), t1 + params.reach_s)))
        return out
    return spans_of(rest), spans_of((still[0] | still[1]) & bouts)


def _runs_while_swinging(mask: np.ndarray, t_s: np.ndarray, swings_s: np.ndarray, params: WornParams
                         ) -> list[tuple[float, float]]:
    """``(t0, t1)`` [s] of the runs of ``mask`` lasting ``min_rest_s`` or more during which the other leg swings
    (``swings_s``, sorted) at least ``min_swings`` times."""
    out = []
    for a, b in true_runs(mask):
        t0, t1 = float(t_s[a]), float(t_s[b - 1])
        if t1 - t0 >= params.min_rest_s and \
                np.searchsorted(swings_s, t1) - np.searchsorted(swings_s, t0) >= params.min_swings:
            out.append((t0, t1))
    return out


def _settled_s(leg: LegInput, standing: np.ndarray, params: WornParams) -> np.ndarray:
    """Sorted times [s] at which the leg was surely on the body: quiet upright standing, a mid-swing within one of its
    walking bouts, or just after one of its strides' end (the removal's own turning makes no whole stride)."""
    t_s = leg.prep.t_s
    ev = leg.events
    ends = t_s[[c for _, _, c in ev.strides]] if ev.strides else np.empty(0)
    swings = t_s[ev.ms[(ev.ms >= 0) & (ev.bout >= 0)]]
    return np.sort(np.concatenate([t_s[standing], swings, ends + params.after_stride_s]))


def _back_to(settled: np.ndarray, t0: float, first_s: float, params: WornParams) -> float:
    """Where a stretch found at ``t0`` starts: the last settled moment before it, at most ``reach_s`` back."""
    k = int(np.searchsorted(settled, t0))
    return min(t0, max(float(settled[k - 1]) if k else first_s, t0 - params.reach_s))


def pieces_s(handled: Sequence[tuple[float, float]], t_first: float, t_last: float,
             params: WornParams = WALKING.worn) -> list[tuple[float, float]]:
    """The stretches ``(t0, t1)`` [s] between ``t_first``, the ``handled`` spans and ``t_last`` that last at least
    ``min_piece_s``: what the session processes each on its own (a mounting can change only where the sensors were
    handled)."""
    out, t = [], t_first
    for t0, t1 in [*handled, (t_last, t_last)]:
        if t0 - t >= params.min_piece_s:
            out.append((t, t0))
        t = max(t, t1)
    return out


def joined(first: LegResult, parts: list[tuple[LegResult, np.ndarray]]) -> tuple[LegResult, np.ndarray]:
    """One leg's result from its pieces processed apart (``parts``: result and mid-swing times [s], in time order):
    traces, strides, gaps and swings in sequence, the counts summed, the other diagnostics from the piece with the
    most strides; ``first`` (the leg processed whole), blank, when no piece could be processed. A piece without a
    gait stride of its own shows no angle (its axes and level have nothing to be learned from, as
    ``pipeline.session._withhold_unanchored`` rules for a whole leg)."""
    if not parts:
        return blanked(first, [(float(first.t_s[0]), float(first.t_s[-1]))], ()), np.empty(0)
    shown = [p.diagnostics is None or p.diagnostics.gait_strides > 0 for p, _ in parts]
    angle = np.concatenate([p.angle_deg if ok else np.full_like(p.angle_deg, np.nan)
                            for (p, _), ok in zip(parts, shown, strict=True)])
    estimator = np.concatenate([p.estimator if ok else np.full(p.estimator.shape, "", dtype=p.estimator.dtype)
                                for (p, _), ok in zip(parts, shown, strict=True)])
    strides = [dataclasses.replace(st, index=i) for i, st in
               enumerate(st for (p, _), ok in zip(parts, shown, strict=True) if ok for st in p.strides)]
    base = max((p for p, _ in parts), key=lambda p: len(p.strides))
    diag = base.diagnostics
    diags = [p.diagnostics for p, _ in parts if p.diagnostics is not None]
    if diag is not None:
        changed = [d.mounting for d in diags if d.mounting is not None and d.mounting.changed]
        diag = dataclasses.replace(
            diag, n_strides=len(strides), n_fallback=sum(1 for st in strides if st.fallback),
            gait_strides=sum(d.gait_strides for d in diags),
            lowered_strides=sum(d.lowered_strides for d in diags), bouts=sum(d.bouts for d in diags),
            bridged_gaps=sum(d.bridged_gaps for d in diags),
            masked_implausible_samples=sum(d.masked_implausible_samples for d in diags),
            clock_disagreement=any(d.clock_disagreement for d in diags),
            mounting=changed[0] if changed else diag.mounting)
    return dataclasses.replace(
        base, t_s=np.concatenate([p.t_s for p, _ in parts]), angle_deg=angle, estimator=estimator, strides=strides,
        gaps_s=[g for p, _ in parts for g in p.gaps_s], walking_s=float(sum(st.duration_s for st in strides)),
        diagnostics=diag), np.concatenate([sw for _, sw in parts])


def blanked(lr: LegResult, spans: Sequence[tuple[float, float]], handled: Sequence[tuple[float, float]]
            ) -> LegResult:
    """``lr`` showing nothing inside ``spans`` [s]: angles NaN, no stride touching one, the spans among its gaps and
    in its diagnostics (``not_worn_s``; ``handled_s``: those in which the sensors were handled)."""
    starts, ends = (np.asarray([sp[k] for sp in spans], dtype=float) for k in (0, 1))
    off = ranges_mask(lr.t_s.size, np.searchsorted(lr.t_s, starts, side="left"),
                      np.searchsorted(lr.t_s, ends, side="right"))
    # spans are disjoint and in order: a stride touches one iff the last span starting before its end outlasts its start
    k = np.searchsorted(starts, [st.t_end_s for st in lr.strides], side="left")
    lr = lr.without({i for i, (st, kk) in enumerate(zip(lr.strides, k, strict=True))
                     if kk > 0 and ends[kk - 1] > st.t_start_s})
    diag = lr.diagnostics
    if diag is not None:
        diag = dataclasses.replace(diag, not_worn_s=tuple(spans), handled_s=tuple(handled))
    return dataclasses.replace(lr, angle_deg=np.where(off, np.nan, lr.angle_deg),
                               estimator=np.where(off, "", lr.estimator),
                               gaps_s=merged_intervals([*lr.gaps_s, *spans]), diagnostics=diag)
