"""Sensors that are not on the leg: a rest in a posture nobody walks in, while the other leg walks.

A knee angle from two sensors is only a knee angle while both are strapped to the leg. Taken off and left on a
table (a strap that chafes, a charger, a shower), they keep recording: still, gravity only, in whatever orientation
they lie. The posture module (:mod:`pipeline.posture`) then reads that as a rest, and the trace shows the table's
"angle" (on a sixth independent simulator and ours, 36-110 deg RMSE against the knee the person kept walking on);
the removal itself, a few seconds of turning unlike any knee, enters the session's hinge fit and moves the axes of
the whole leg (ours: the same leg's trace 6 deg off before the removal).

The physical test: nobody walks on one leg while the other sits or lies still. A run of at least ``min_rest_s`` in
which this leg rests (:func:`pipeline.posture.quiet_mask`, outside its own walking bouts) and is not standing
upright (:func:`pipeline.posture.standing_mask`), during which the other leg's shank swings at least
``min_swings`` times, is a stretch without the sensors on the leg. Standing on this leg while the other one swings
(one-legged exercises) is a posture a body holds, and does not count. The stretch reaches back to the last moment
the leg was surely on the body, quiet upright standing or the end of a stride (the removal's own turning makes no
whole stride), and on to its first swing after the rest (the sensors taken off and put back on), by at most
``reach_s``. No paper gives these rules.

What the session does with the stretches (:mod:`pipeline.session`): the leg is processed again without them (a
long hole: nothing there is estimated, and the hinge fit no longer sees the removal); the other leg's strides there
are still judged against this leg's stillness, so a lying or seated one-legged exercise cannot become gait.
"""

from __future__ import annotations

import numpy as np

from pipeline.bilateral import OtherLeg
from pipeline.leg_input import LegInput
from pipeline.params import WALKING, WornParams
from pipeline.posture import in_bouts, leg_quiet, standing_mask
from pipeline.signal_utils import true_runs


def not_worn_spans_s(leg: LegInput, other: OtherLeg | None, params: WornParams = WALKING.worn
                     ) -> list[tuple[float, float]]:
    """Time spans ``(t0, t1)`` [s, the leg's clock] in which the leg's sensors were not on the leg (module
    docstring), in order and disjoint; empty without the other leg's swings."""
    if other is None or other.swings_s.size < params.min_swings:
        return []
    prep = leg.prep
    t_s = prep.t_s
    quiet = leg_quiet(leg)
    bouts = in_bouts(leg)
    standing = standing_mask(leg, quiet, bouts)
    rest = quiet & ~bouts & ~standing
    ev = leg.events
    own = np.sort(t_s[ev.ms[ev.ms >= 0]])
    ends = np.sort(t_s[[c for _, _, c in ev.strides]]) if ev.strides else own
    # when the leg was surely on the body: quiet upright standing, or just after a stride's end
    settled = np.sort(np.concatenate([t_s[standing], ends + params.after_stride_s]))
    spans: list[tuple[float, float]] = []
    for a, b in true_runs(rest):
        t0, t1 = float(t_s[a]), float(t_s[b - 1])
        if t1 - t0 < params.min_rest_s:
            continue
        n_other = int(np.searchsorted(other.swings_s, t1) - np.searchsorted(other.swings_s, t0))
        if n_other < params.min_swings:
            continue
        k = int(np.searchsorted(settled, t0))
        m = int(np.searchsorted(own, t1, side="right"))
        t0 = min(t0, max(float(settled[k - 1]) if k else float(t_s[0]), t0 - params.reach_s))
        t1 = min(float(own[m]) if m < own.size else float(t_s[-1]), t1 + params.reach_s)
        if spans and t0 <= spans[-1][1]:
            spans[-1] = (spans[-1][0], max(spans[-1][1], t1))
        else:
            spans.append((t0, t1))
    return spans
