"""Raw thigh + shank streams of one leg -> SI units on one uniform time grid, with packet-loss gaps marked.

Thigh and shank IMUs are not sample-synchronous and may run at different rates, so both are interpolated onto one
grid at the faster of the two rates by a cubic Hermite (Catmull-Rom) curve: gait signals are smooth at 50-200 Hz and
a cubic keeps swing peaks that straight lines would cut. A gap is a step between consecutive samples longer than
``PrepareParams.gap_factor`` nominal periods. Gaps up to ``PrepareParams.max_bridge_s`` (one or two lost BLE
packets; shorter than the swing-flexion phase, so the cubic still sees both sides of any knee event) are bridged by
the cubic and reported (``bridged_s``, strides touching one get a quality note); those longer than
``PrepareParams.noted_bridge_s`` inside periodic gait are filled from the sensor's own neighbouring strides instead,
warped to the hole's own timing (:func:`periodic_fill`, reported in ``filled_s``), and so are longer gaps up to
``PrepareParams.periodic_bridge_s`` (those beyond ``PrepareParams.one_sided_fill_s`` only with gait on both sides;
strides touching them stay out of trends, :mod:`pipeline.quality`); the rest is masked: no angle, no stride across.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.constants import G_MPS2
from pipeline.kernels import central_slopes, hermite_eval, saturated_runs, shifted_context, si_block
from pipeline.params import WALKING, PostureParams, PrepareParams
from pipeline.rest_offset import rest_offsets
from pipeline.signal_utils import merged_intervals
from pipeline.types import RawSensorStream

MAX_BRIDGE_S = WALKING.prepare.max_bridge_s
"""The walking preset's bridge limit [s], for callers outside the pipeline (:class:`PrepareParams` owns it)."""
EDGE_TOL_S = 1e-6
"""A grid sample this close to a gap's edge [s] is the received sample there: the grid is anchored on received
stamps, so whether an edge sample is kept must not depend on the last bit of a clock correction (one sample more or
less moves the fits' sample sets, and so stride edges and peaks). Far below any sample period, far above rounding."""


@dataclass(frozen=True)
class PreparedLeg:
    """One leg on a uniform grid ``t_s = t0_s + i / fs_hz``. Segment 1 is the thigh, 2 the shank (Seel et al. 2014
    numbering; Rhudy et al. 2024 swap them)."""

    leg: str
    fs_hz: float
    t0_s: float
    t_s: np.ndarray
    gyr_thigh_rps: np.ndarray
    gyr_shank_rps: np.ndarray
    acc_thigh_mps2: np.ndarray
    acc_shank_mps2: np.ndarray
    valid: np.ndarray  # False inside masked gaps
    saturated: np.ndarray  # True where either gyro looks saturated
    gaps_s: list[tuple[float, float]] = field(default_factory=list)
    bridged_gaps: int = 0
    bridged_s: list[tuple[float, float]] = field(default_factory=list)  # bridged gaps worth a quality note
    # gaps filled from the neighbouring strides (:func:`periodic_fill`): valid, but the samples are a model
    filled_s: list[tuple[float, float]] = field(default_factory=list)
    # the thigh's own masked and filled gaps, so a re-stamped shank can reuse the thigh channels (on this grid, or cut
    # to the part the re-stamped shank covers)
    thigh_gaps_s: list[tuple[float, float]] = field(default_factory=list)
    thigh_filled_s: list[tuple[float, float]] = field(default_factory=list)
    thigh_noted_s: list[tuple[float, float]] = field(default_factory=list)
    shank_bridged: int = 0
    thigh_saturated: np.ndarray | None = None  # the thigh's part of ``saturated``, for the same reuse
    # each sensor's accelerometer offset [m/s^2] and gyro bias [rad/s] seen at rest (pipeline.rest_offset), already
    # removed from acc_*_mps2 and gyr_*_rps
    acc_offset_thigh_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_offset_shank_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyr_bias_thigh_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyr_bias_shank_rps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    shank_saturated_raw: np.ndarray | None = None  # the shank's saturated raw samples (its own stamps)

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    def measured(self) -> np.ndarray:
        """``valid`` without the holes filled from the neighbouring strides: where both sensors' samples are
        their own, for cues that compare the two sensors' timing (a fill's timing is its neighbours')."""
        return self.valid & ~_mask_intervals(self.t_s, self.filled_s) if self.filled_s else self.valid


SI = tuple[np.ndarray, np.ndarray, np.ndarray]
"""``(t_s, gyr_rps, acc_mps2)`` of one stream: what :func:`to_si` returns."""


def to_si(stream: RawSensorStream) -> SI:
    """``(t_s, gyr_rps, acc_mps2)`` of a raw stream, sorted by time with duplicate time stamps dropped."""
    t = np.asarray(stream.t_s, dtype=float)
    gyr = np.asarray(stream.gyr, dtype=float).reshape(-1, 3)
    acc = np.asarray(stream.acc, dtype=float).reshape(-1, 3)
    if not (t.shape[0] == gyr.shape[0] == acc.shape[0]):
        raise ValueError(f"sensor {stream.sensor_id}: t_s, gyr and acc have different lengths "
                         f"({t.shape[0]}, {gyr.shape[0]}, {acc.shape[0]})")
    if stream.gyro_unit not in ("deg/s", "rad/s"):
        raise ValueError(f"sensor {stream.sensor_id}: unknown gyro unit {stream.gyro_unit!r}")
    if stream.acc_unit not in ("g", "m/s2"):
        raise ValueError(f"sensor {stream.sensor_id}: unknown accelerometer unit {stream.acc_unit!r}")
    # both converted into the halves of one (N, 6) array, the layout the resampling takes (:func:`_channels`),
    # so that neither the conversion nor the resampling needs a copy of its own
    both = np.empty((t.shape[0], 6))
    fast = si_block is not None and t.shape[0] >= 2
    # deg2rad is the product with pi / 180 (as numpy computes it); a scale of 1.0 copies
    if fast and si_block(np.ascontiguousarray(t), gyr, acc, np.pi / 180.0 if stream.gyro_unit == "deg/s" else 1.0,
                         G_MPS2 if stream.acc_unit == "g" else 1.0, both):
        return t, both[:, :3], both[:, 3:]  # the usual case: finite, sorted and unique
    if not fast:
        if stream.gyro_unit == "deg/s":
            np.deg2rad(gyr, out=both[:, :3])
        else:
            both[:, :3] = gyr
        if stream.acc_unit == "g":
            np.multiply(acc, G_MPS2, out=both[:, 3:])
        else:
            both[:, 3:] = acc
    # whole-array finiteness first: the row-wise all(axis=1) over (N, 6) is slow and rarely needed
    if not (np.isfinite(t).all() and np.isfinite(both).all()):
        finite = np.isfinite(t) & np.isfinite(both).all(axis=1)
        t, both = t[finite], both[finite]
    if t.shape[0] < 2 or np.all(np.diff(t) > 0):
        return t, both[:, :3], both[:, 3:]  # the usual case: already sorted and unique (or nothing to sort)
    order = np.argsort(t, kind="stable")
    t, both = t[order], both[order]
    keep = np.concatenate(([True], np.diff(t) > 0))
    t, both = t[keep], both[keep]
    return t, both[:, :3], both[:, 3:]


def _channels(gyr: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """``np.hstack([gyr, acc])``: the (N, 6) array of :func:`to_si` itself when ``gyr`` and ``acc`` are still its two
    halves (no copy), else the stacked copy."""
    base = gyr.base
    if (isinstance(base, np.ndarray) and base is acc.base and base.dtype == np.float64 and base.flags.c_contiguous
            and base.shape == (gyr.shape[0], 6) and gyr.shape == acc.shape == (base.shape[0], 3)
            and gyr.__array_interface__["data"][0] == base.__array_interface__["data"][0]
            and acc.__array_interface__["data"][0] == base.__array_interface__["data"][0] + 3 * base.itemsize):
        return base
    return np.hstack([gyr, acc])


def nominal_fs(stream: RawSensorStream, t_s: np.ndarray) -> float:
    """The declared rate, unless the time stamps clearly disagree (then the median sample spacing wins, but never
    above twice the declared rate: near-duplicate stamps must not blow the grid up to millions of samples)."""
    declared = float(stream.fs_hz) if stream.fs_hz and stream.fs_hz > 0 else 0.0
    if t_s.shape[0] < 2:
        return declared or 100.0
    measured = 1.0 / float(np.median(np.diff(t_s)))
    if declared and (abs(measured - declared) / declared < 0.2 or measured > 2.0 * declared):
        return declared
    return measured


def find_gaps(t_s: np.ndarray, fs_hz: float, params: PrepareParams = WALKING.prepare
              ) -> tuple[list[tuple[float, float]], int, list[tuple[float, float]]]:
    """Masked gaps ``(t_last_before, t_first_after)`` longer than ``max_bridge_s``, the number of bridged gaps, and
    the bridged gaps longer than ``noted_bridge_s`` (worth a note on the strides they touch)."""
    dt = np.diff(t_s)
    is_gap = dt > params.gap_factor / fs_hz
    long_gap = is_gap & (dt > params.max_bridge_s)
    noted = np.flatnonzero(is_gap & ~long_gap & (dt > params.noted_bridge_s))
    idx = np.flatnonzero(long_gap)
    return ([(float(t_s[i]), float(t_s[i + 1])) for i in idx], int(is_gap.sum() - long_gap.sum()),
            [(float(t_s[i]), float(t_s[i + 1])) for i in noted])


def saturation_mask(gyr: np.ndarray, params: PrepareParams = WALKING.prepare) -> np.ndarray:
    """Samples where some gyro axis (``gyr`` (N, 3) [rad/s]) sits at its extreme value (within
    ``saturation_tol`` of it) for ``saturation_run`` samples in a row (clipped sensor)."""
    run_len = params.saturation_run
    out = np.zeros(gyr.shape[0], dtype=bool)
    # the peaks first: most recordings never come near a clipping range, and then no axis needs more. One column at
    # a time: a maximum over axis 0 of an (N, 3) array runs numpy's inner loop once per row, ten times slower (the
    # maximum is exact, so the same peaks)
    peaks = np.array([np.abs(gyr[:, axis]).max(initial=0.0) for axis in range(gyr.shape[1])])
    if saturated_runs is not None and gyr.shape[0] >= run_len:
        # the axes worth testing get their threshold (as below), the others none
        thr = np.where(np.rad2deg(peaks) < params.saturation_min_dps, np.nan, peaks * (1.0 - params.saturation_tol))
        saturated_runs(gyr, thr, int(run_len), out)
        return out
    for axis in range(3):
        peak = peaks[axis]
        if np.rad2deg(peak) < params.saturation_min_dps:
            continue
        g = np.abs(gyr[:, axis])
        at_peak = g >= peak * (1.0 - params.saturation_tol)
        run = np.convolve(at_peak.astype(int), np.ones(run_len, dtype=int), mode="same") >= run_len
        if run.any():
            out |= np.convolve(run.astype(int), np.ones(run_len, dtype=int), mode="same") > 0
    return out


def _mask_on_grid(t_grid: np.ndarray, t_s: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A raw sample mask (at stamps ``t_s``) on the grid: True where the straight line between the neighbouring raw
    samples' flags is above zero, i.e. next to a flagged sample. Without a flagged sample that line is zero
    everywhere, so no interpolation is needed (the usual case: clipped gyros are rare)."""
    if not mask.any():
        return np.zeros(t_grid.shape[0], dtype=bool)
    return np.interp(t_grid, t_s, mask.astype(float)) > 0


_INTERP_BLOCK = 16384
"""Grid samples interpolated per block: the block's (6, rows) temporaries stay in cache (the whole grid's do not);
each value is computed the same way, so blocking does not change it."""


def _interp_columns(t_new: np.ndarray, t: np.ndarray, x: np.ndarray, max_bridge_s: float) -> np.ndarray:
    """Cubic Hermite interpolation (Catmull-Rom slopes from the neighbouring samples, non-uniform times), fully
    vectorised; straight lines across gaps longer than ``max_bridge_s`` (masked anyway, but no overshoot)."""
    n = t.shape[0]
    if n < 4:
        return np.column_stack([np.interp(t_new, t, x[:, k]) for k in range(x.shape[1])])
    dt = np.diff(t)
    long_gap = dt > max_bridge_s
    n_new = t_new.shape[0]
    out = np.empty((n_new, x.shape[1]))
    if hermite_eval is not None and central_slopes is not None and np.isfinite(t_new).all():
        x = np.ascontiguousarray(x, dtype=float)
        t = np.ascontiguousarray(t, dtype=float)
        m = np.empty_like(x)
        central_slopes(t, x, m)
        _one_sided_slopes(m, x, dt, long_gap)
        i_all = np.empty(n_new, dtype=np.int64)
        hermite_eval(np.ascontiguousarray(t_new, dtype=float), t, x, m, dt, i_all, out)
        return _straight_across_gaps(out, t_new, t, x, dt, long_gap, i_all)
    # slopes: central differences inside, one-sided at the ends and next to long gaps. Computed and gathered with
    # the channels as rows ((C, N), each channel's samples contiguous): the gathers then copy single values with
    # numpy's fast path instead of one 48-byte row at a time, and the products run along contiguous rows
    xt = np.ascontiguousarray(x.T)
    mt = np.empty_like(xt)
    mt[:, 1:n - 1] = (xt[:, 2:] - xt[:, :-2]) / (t[2:] - t[:-2])
    _one_sided_slopes(mt.T, x, dt, long_gap)
    i_all = np.clip(np.searchsorted(t, t_new, side="right") - 1, 0, n - 2)
    block = min(_INTERP_BLOCK, n_new)
    scratch, block_out = np.empty((x.shape[1], block)), np.empty((x.shape[1], block))
    for a in range(0, n_new, block):
        b = min(a + block, n_new)
        i = i_all[a:b]
        h = dt[i]
        u = (t_new[a:b] - t[i]) / h
        u2, u3 = u * u, u * u * u
        # same sums in the same order as the textbook one-liner (h00 x0 + h10 h m0 + h01 x1 + h11 h m1),
        # accumulated in place with one scratch array
        o, tmp = block_out[:, :b - a], scratch[:, :b - a]
        np.take(xt, i, axis=1, out=tmp)
        np.multiply(2 * u3 - 3 * u2 + 1, tmp, out=o)
        np.take(mt, i, axis=1, out=tmp)
        tmp *= (u3 - 2 * u2 + u) * h
        o += tmp
        np.take(xt, i + 1, axis=1, out=tmp)
        tmp *= -2 * u3 + 3 * u2
        o += tmp
        np.take(mt, i + 1, axis=1, out=tmp)
        tmp *= (u3 - u2) * h
        o += tmp
        out[a:b] = o.T
    return _straight_across_gaps(out, t_new, t, x, dt, long_gap, i_all)


def _one_sided_slopes(m: np.ndarray, x: np.ndarray, dt: np.ndarray, long_gap: np.ndarray) -> None:
    """One-sided slopes in ``m`` at both ends and next to long gaps (from the data on the gap's own side)."""
    n = x.shape[0]

    def one_sided(k: np.ndarray | int) -> np.ndarray:
        """Slope of interval ``k`` (``x[k] -> x[k + 1]``), only where it is needed."""
        return (x[k + 1] - x[k]) / np.asarray(dt[k])[..., None]

    m[0], m[-1] = one_sided(0), one_sided(n - 2)
    g = np.flatnonzero(long_gap)
    m[g] = one_sided(np.maximum(g - 1, 0))  # one-sided: the data before the gap
    m[g + 1] = one_sided(np.minimum(g + 1, n - 2))  # and after it


def _straight_across_gaps(out: np.ndarray, t_new: np.ndarray, t: np.ndarray, x: np.ndarray, dt: np.ndarray,
                          long_gap: np.ndarray, i_all: np.ndarray) -> np.ndarray:
    """``out`` with the grid samples inside long gaps on the straight line between the gap's edge samples."""
    lin = long_gap[i_all]
    if lin.any():
        il = i_all[lin]
        x0, x1 = x[il], x[il + 1]
        u = (t_new[lin] - t[il]) / dt[il]
        out[lin] = x0 + u[:, None] * (x1 - x0)
    return out


def periodic_fill(t_grid: np.ndarray, x: np.ndarray, gaps: list[tuple[float, float]], fs_hz: float,
                  params: PrepareParams = WALKING.prepare, bridged: list[tuple[float, float]] | None = None
                  ) -> tuple[np.ndarray, list[tuple[float, float]], list[tuple[float, float]]]:
    """Fill one sensor's gaps ``(t_last_before, t_first_after)`` on the grid ``t_grid`` from its neighbouring strides.

    Gait is periodic: a shank or thigh IMU's signal one stride earlier and later predicts the missing one well
    (stride-to-stride correlation of the shank rate > 0.9 in steady walking). The stride period T is the lag in
    ``periodic_period_s`` that best aligns the ``periodic_context_s`` of data on both sides of the hole with the same
    data shifted by T (the autocorrelation period estimate of gait cycles, Moe-Nilssen and Helbostad 2004); where
    only one side is gait (the hole at a bout's first or last stride), that side alone with the stride on its side.
    The template is the stride one period before and/or after (what is wholly available), warped in time: its
    shift is fitted separately to the ``periodic_edge_s`` of data at either edge of the hole and runs linearly
    between them (piecewise-linear registration of gait cycles, Sadeghi et al. 2000), since consecutive strides
    differ in timing by a few per cent. A straight line then matches the template to the measured samples at both
    edges. ``x`` (N, C): the sensor's grid channels, gyro in the first three (the only ones scored). A gap longer
    than ``periodic_bridge_s``, without periodic context (correlation below ``periodic_min_corr``) or at the grid's
    edge stays a gap. ``bridged``: holes already bridged by the cubic (``x`` holds it there), filled the same way
    where the neighbouring strides allow (a cubic through a 0.1 s hole on the swing-flexion rise misses the rise by
    degrees, the neighbouring strides do not) and left to the cubic elsewhere. Returns the filled channels, the
    filled gaps (bridged ones included) and the remaining gaps (of ``gaps`` only)."""
    bridged = bridged or []
    if not gaps and not bridged:
        return x, [], []
    optional = set(bridged)
    gaps = sorted([*gaps, *bridged])
    n = t_grid.shape[0]
    bad = _mask_intervals(t_grid, gaps)
    lags = np.arange(max(int(params.periodic_period_s[0] * fs_hz), 1), int(params.periodic_period_s[1] * fs_hz) + 1)
    ctx = max(int(params.periodic_context_s * fs_hz), 2)
    edge = max(int(round(params.periodic_edge_s * fs_hz)), 3)
    step = max(int(round(fs_hz / params.periodic_search_hz)), 1)
    out = x
    filled: list[tuple[float, float]] = []
    kept: list[tuple[float, float]] = []
    los, his = _inside_bounds(t_grid, np.array([g[0] for g in gaps]), np.array([g[1] for g in gaps]))
    holes = list(zip(gaps, los.tolist(), his.tolist(), strict=True))
    k = 0
    while k < len(holes):
        group = _adjacent_holes(holes, k, t_grid)
        k += len(group)
        (g0, _), i0, _ = group[0]
        (_, g1), _, i1 = group[-1]
        fill = None
        if i1 > i0 and g1 - g0 <= params.periodic_bridge_s and i0 >= 1 and i1 < n:
            fill = _periodic_hole(x, bad, i0, i1, lags, ctx, edge, step, params,
                                  one_sided=g1 - g0 <= params.one_sided_fill_s)
        if fill is not None:
            if out is x:
                out = x.copy()
            out[i0:i1] = fill
        if fill is not None and len(group) > 1:
            filled.append((g0, g1))  # the grid samples between the holes were overwritten too
        for gap, j0, j1 in group:
            if fill is None and gap in optional:
                continue  # left to the cubic
            if fill is not None or j1 <= j0:  # filled, or no grid sample inside: nothing to fill
                filled.append(gap)
            else:
                kept.append(gap)
    return out, filled, kept


def _adjacent_holes(holes: list[tuple[tuple[float, float], int, int]], k: int, t_grid: np.ndarray
                    ) -> list[tuple[tuple[float, float], int, int]]:
    """Hole ``k`` (``(gap, first grid index inside, end)``) with the holes after it that no measured grid sample
    separates from it: none between, or one that is not the lone received sample between them (off the grid, it
    is interpolated across both holes). One hole for the fill, whose edge samples must be measured."""
    group = [holes[k]]
    while k + len(group) < len(holes):
        nxt = holes[k + len(group)]
        (_, g1), i0, end = group[-1]
        if nxt[2] <= nxt[1] or end <= i0:
            break
        between = nxt[1] - end  # grid samples outside both holes
        if between > 1 or (between == 1 and abs(float(t_grid[end]) - g1) <= EDGE_TOL_S):
            break
        group.append(nxt)
    return group


_CANDIDATE_LAGS = 8
"""Best-scoring periods tried in turn until one's template is wholly available (a neighbouring stride may have a
hole of its own at the same phase)."""


def _periodic_hole(x: np.ndarray, bad: np.ndarray, i0: int, i1: int, lags: np.ndarray, ctx: int, edge: int,
                   step: int, params: PrepareParams, one_sided: bool = True) -> np.ndarray | None:
    """Samples ``[i0, i1)`` of ``x`` from the best-aligned neighbouring strides (:func:`periodic_fill`), None
    without them. ``one_sided``: the context of one side alone may do (``PrepareParams.one_sided_fill_s``); else
    each side's own context must repeat. The period is searched on every ``step``-th lag and context sample; the
    template's edge shifts (:func:`_warped_template`) then align it to the sample and below."""
    n = x.shape[0]
    pre = np.arange(max(i0 - ctx, 0), i0)
    pre = pre[~bad[pre]]
    post = np.arange(i1, min(i1 + ctx, n))
    post = post[~bad[post]]
    g = x[:, :3]
    h = np.arange(i0 - 1, i1 + 1)  # the hole with its measured edge samples
    coarse = lags[::step]
    scores = _context_scores(g, bad, pre[::-step][::-1], post[::step], coarse)
    none = pre[:0]
    min_corr = params.periodic_min_corr
    # (which context scores, per direction: its sign and the context it may align its edges on)
    tries: list[tuple[str, tuple[tuple[int, np.ndarray, np.ndarray], ...]]] = []
    if pre.size + post.size >= ctx:
        tries.append(("both", ((-1, pre, post), (1, pre, post))))
    if one_sided and pre.size >= ctx // 2:  # the hole at a bout's end: the stride before it alone
        tries.append(("pre", ((-1, pre, none),)))
    if one_sided and post.size >= ctx // 2:  # at a bout's start: the stride after it alone
        tries.append(("post", ((1, none, post),)))
    for which, directions in tries:
        score = np.max([scores[which, sign] for sign, _, _ in directions], axis=0)
        for k in np.argsort(-score, kind="stable")[:_CANDIDATE_LAGS]:
            if not score[k] >= min_corr:
                break
            lag = int(coarse[k])
            # a direction whose own context does not repeat (the stride after the bout's last one) is left out
            sides = [(sign, before, after) for sign, before, after in directions if scores[which, sign][k] >= min_corr]
            if not one_sided and min(max(scores[s, -1][k], scores[s, 1][k]) for s in ("pre", "post")) < min_corr:
                continue  # a long hole needs gait on both sides: each side's own context repeats
            if len(directions) == 1:
                # one side of context is less selective than two (a slow drift matches itself one lag away as
                # well), so gait must repeat once more: the same context two periods away matches too
                sign, before, after = sides[0]
                side = before if sign < 0 else after
                if not _correlation(g, bad, side, 2 * sign * lag) >= min_corr:
                    continue
            tmpl = [t for t in (_warped_template(x, g, bad, h, lag, sign, before, after, edge,
                                                 params.periodic_max_warp) for sign, before, after in sides)
                    if t is not None]
            if tmpl:
                fill = tmpl[0] if len(tmpl) == 1 else 0.5 * (tmpl[0] + tmpl[1])
                r0, r1 = x[i0 - 1] - fill[0], x[i1] - fill[-1]
                u = (np.arange(1, h.size - 1) / (h.size - 1))[:, None]
                return fill[1:-1] + (1 - u) * r0 + u * r1
    return None


def _context_scores(g: np.ndarray, bad: np.ndarray, pre: np.ndarray, post: np.ndarray, lags: np.ndarray
                    ) -> dict[tuple[str, int], np.ndarray]:
    """Correlation per lag of the context before (``pre``), after (``post``) and on both sides of a hole with the
    same samples one lag earlier (sign -1) and later (+1); masked samples are left out and a lag that loses more
    than half of a context scores -inf. Keys ``(side, sign)``."""
    n = g.shape[0]
    c = np.concatenate((pre, post))
    out: dict[tuple[str, int], np.ndarray] = {}
    if c.size == 0:
        return {(side, sign): np.full(lags.size, -np.inf) for side in ("both", "pre", "post") for sign in (-1, 1)}
    mean = g[c].mean(axis=0)
    a = g[c] - mean
    a2s = np.sum(a ** 2, axis=1)
    fast = shifted_context is not None and bad.dtype == np.bool_ and bad.flags.c_contiguous
    # the rows any shift can reach, centred once: g[k] - mean is the same difference whether taken before or after
    # the gather, and these few hundred rows stay in cache (the (lags, context, 3) products are ten times larger)
    lo, hi = max(int(c[0]) - int(lags[-1]), 0), min(int(c[-1]) + int(lags[-1]) + 1, n)
    centred = None if fast else g[lo:hi] - mean
    k = pre.size
    for sign in (-1, 1):
        if fast:
            b = np.empty((lags.size, c.size, 3))
            ok = np.empty((lags.size, c.size), dtype=bool)
            shifted_context(g, bad, c.astype(np.int64, copy=False), np.ascontiguousarray(lags, dtype=np.int64), sign,
                            np.ascontiguousarray(mean, dtype=float), b, ok)
        else:
            src = c[None, :] + sign * lags[:, None]  # (lags, context)
            ok = _measured_at(bad, src)
            b = centred[np.clip(src, lo, hi - 1) - lo]  # (lags, context, 3)
            b *= ok[:, :, None]  # the masked terms are zero, as the compiled loop leaves them
        # the three sums of the correlation per side, as matrix-vector products over each side's (context, axis)
        # block (a reduction over numpy's last axis of 3 would run its inner loop once per row); both sides: the sum
        okf = ok.astype(float)
        parts = []
        for sl in (slice(0, k), slice(k, None)):
            bs = b[:, sl].reshape(lags.size, -1)
            parts.append((bs @ a[sl].reshape(-1), okf[:, sl] @ a2s[sl], np.einsum("ij,ij->i", bs, bs),
                          okf[:, sl].sum(axis=1), max(okf[:, sl].shape[1], 1)))
        (n0, a0, b0, c0, _), (n1, a1, b1, c1, _) = parts
        for side, (nu, da, db, cnt, m) in (("pre", parts[0]), ("post", parts[1]),
                                           ("both", (n0 + n1, a0 + a1, b0 + b1, c0 + c1, c.size))):
            with np.errstate(invalid="ignore", divide="ignore"):
                r = nu / np.sqrt(da * db)
            r[~((cnt >= 0.5 * m) & np.isfinite(r))] = -np.inf
            out[side, sign] = r
    return out


def _measured_at(bad: np.ndarray, src: np.ndarray) -> np.ndarray:
    """For indices ``src`` (any shape), whether each lies inside the signal and outside its holes ``bad``."""
    ok = (src >= 0) & (src < bad.shape[0])
    ok[ok] = ~bad[src[ok]]
    return ok


def _correlation(g: np.ndarray, bad: np.ndarray, idx: np.ndarray, offset: int) -> float:
    """Correlation of ``g[idx]`` with ``g[idx + offset]`` over the pairs with both samples valid, each centred on
    its own mean; -inf with fewer than half of ``idx`` paired."""
    src = idx + offset
    ok = _measured_at(bad, src)
    if ok.sum() < max(idx.size // 2, 3):
        return -np.inf
    a = g[idx[ok]] - g[idx[ok]].mean(axis=0)
    b = g[src[ok]] - g[src[ok]].mean(axis=0)
    den = float(np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return float(np.sum(a * b)) / den if den > 0 else -np.inf


def _warped_template(x: np.ndarray, g: np.ndarray, bad: np.ndarray, h: np.ndarray, lag: int, sign: int,
                     pre: np.ndarray, post: np.ndarray, edge: int, max_warp: float) -> np.ndarray | None:
    """The stride ``sign * lag`` samples away at the hole's samples ``h`` (with its edge samples), shifted at each
    edge by what best aligns the last ``edge`` context samples before the hole (``pre``) and the first after it
    (``post``) with it (to within ``max_warp`` of the lag) and linearly in between; one side's shift for both
    where only one is known. Linear interpolation between samples; None where it needs a masked sample or the
    shifts would fold the template back in time (a short hole whose edges disagree by more than its length)."""
    max_d = max(int(round(max_warp * lag)), 1)
    shifts = [_edge_shift(g, bad, side, sign * lag, max_d) for side in (pre[-edge:], post[:edge])]
    da, db = shifts
    if da is None and db is None:
        da = db = 0.0
    da = db if da is None else da
    db = da if db is None else db
    u = (h - h[0]) / (h[-1] - h[0])
    pos = h + sign * lag + da + (db - da) * u
    if db - da <= 1 - h.size:  # the two edges' shifts would run the template backwards: no alignment
        return None
    i = np.floor(pos).astype(np.int64)
    if i[0] < 0 or i[-1] + 1 >= x.shape[0] or bad[i].any() or bad[i + 1].any():
        return None
    f = (pos - i)[:, None]
    return (1 - f) * x[i] + f * x[i + 1]


def _edge_shift(g: np.ndarray, bad: np.ndarray, idx: np.ndarray, offset: int, max_d: int) -> float | None:
    """Shift d [samples, fractional] within ``+-max_d`` minimising the mean squared difference between ``g[idx]``
    and ``g[idx + offset + d]`` (the minimum refined by a parabola through its neighbours); None with fewer than
    three context samples or without half of them valid at every shift."""
    if idx.size < 3:
        return None
    n = g.shape[0]
    ds = np.arange(-max_d, max_d + 1)
    src = idx[None, :] + offset + ds[:, None]
    ok = _measured_at(bad, src)
    diff = (g[idx][None] - g[np.clip(src, 0, n - 1)]) * ok[:, :, None]
    cnt = ok.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sse = np.where(cnt >= max(idx.size // 2, 3), np.sum(diff * diff, axis=(1, 2)) / cnt, np.inf)
    k = int(np.argmin(sse))
    if not np.isfinite(sse[k]):
        return None
    d = float(ds[k])
    if 0 < k < ds.size - 1 and np.isfinite(sse[k - 1]) and np.isfinite(sse[k + 1]):
        curv = sse[k - 1] - 2 * sse[k] + sse[k + 1]
        if curv > 0:
            d += float(np.clip(0.5 * (sse[k - 1] - sse[k + 1]) / curv, -0.5, 0.5))
    return d


def _inside_bounds(t_grid: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """(2, K) grid index ranges [lo, hi) of the samples strictly inside each interval, by more than ``EDGE_TOL_S``."""
    return np.stack([np.searchsorted(t_grid, starts + EDGE_TOL_S, side="right"),
                     np.searchsorted(t_grid, stops - EDGE_TOL_S, side="left")])


def _mask_intervals(t_grid: np.ndarray, gaps: list[tuple[float, float]]) -> np.ndarray:
    """True for grid samples strictly inside any gap interval."""
    bad = np.zeros(t_grid.shape[0], dtype=bool)
    if not gaps:
        return bad
    lo, hi = _inside_bounds(t_grid, np.array([g[0] for g in gaps]), np.array([g[1] for g in gaps]))
    delta = np.zeros(t_grid.shape[0] + 1, dtype=int)
    np.add.at(delta, lo, 1)
    np.add.at(delta, hi, -1)
    return np.cumsum(delta)[:-1] > 0


def prepare_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, shank_shift_s: float = 0.0,
                shank_drift: float = 0.0, params: PrepareParams = WALKING.prepare,
                posture: PostureParams = WALKING.posture) -> PreparedLeg:
    """Convert both streams to SI, put them on one uniform grid over their common time span, mark gaps, remove
    each sensor's accelerometer offset and gyro bias seen at rest (:mod:`pipeline.rest_offset`, with the rest
    definition of ``posture``).

    The shank's time stamps are corrected to ``t + shank_shift_s + shank_drift * t`` (a measured clock offset and
    rate error, see :func:`pipeline.sync.synchronised_leg`). Raises ValueError when the two streams have no
    usable overlap.
    """
    si1, si2 = to_si(thigh), to_si(shank)
    return prepare_leg_si(leg, si1, si2, nominal_fs(thigh, si1[0]), nominal_fs(shank, si2[0]),
                          shank_shift_s, shank_drift, params=params, posture=posture)


def prepare_leg_si(leg: str, si1: tuple[np.ndarray, np.ndarray, np.ndarray],
                   si2: tuple[np.ndarray, np.ndarray, np.ndarray], fs1: float, fs2: float,
                   shank_shift_s: float = 0.0, shank_drift: float = 0.0, reuse: PreparedLeg | None = None,
                   params: PrepareParams = WALKING.prepare, posture: PostureParams = WALKING.posture) -> PreparedLeg:
    """:func:`prepare_leg` on streams already converted by :func:`to_si` (``(t_s, gyr_rps, acc_mps2)`` each, at
    nominal rates ``fs1``/``fs2``), so a second pass with corrected shank time stamps skips the conversion.
    ``reuse``: a first pass of the same streams; its grid and thigh channels (rest offsets removed) are kept, cut
    to the part of the grid the re-stamped shank still covers (:func:`_kept_grid`): only the shank is interpolated
    again."""
    for name, si in (("thigh", si1), ("shank", si2)):
        if si[0].shape[0] < 2:
            raise ValueError(f"{leg} {name} sensor has fewer than 2 usable samples")
    t1, g1, a1 = si1
    t2, g2, a2 = si2
    if shank_shift_s or shank_drift:
        t2 = t2 + shank_shift_s + shank_drift * t2
    fs_hz = float(max(fs1, fs2))
    t_start, t_stop = max(t1[0], t2[0]), min(t1[-1], t2[-1])
    if t_stop - t_start < 2.0 / fs_hz:
        raise ValueError(f"{leg} leg: thigh and shank recordings do not overlap in time")
    kept = _kept_grid(reuse, t2, fs_hz)
    if kept is not None:
        t_grid = _cut(reuse.t_s, kept)
        t_start = float(t_grid[0])
    else:
        n = int(np.floor((t_stop - t_start) * fs_hz + 1e-9)) + 1
        t_grid = t_start + np.arange(n) / fs_hz
    keep_grid = kept is not None
    if keep_grid and reuse.thigh_saturated is not None:
        sat_thigh = _cut(reuse.thigh_saturated, kept)  # same stamps, same grid: the same samples
    else:
        sat_thigh = _mask_on_grid(t_grid, t1, saturation_mask(g1, params))
    # the shank's samples are the same in a re-stamped pass (only their stamps moved): the same raw mask
    sat_shank = reuse.shank_saturated_raw if reuse is not None and reuse.shank_saturated_raw is not None \
        and reuse.shank_saturated_raw.shape[0] == g2.shape[0] else saturation_mask(g2, params)
    saturated = sat_thigh | _mask_on_grid(t_grid, t2, sat_shank)
    if keep_grid:
        # the first pass's arrays (cut to the kept grid; never modified in place): same values and memory layout
        gyr_thigh, acc_thigh = _cut(reuse.gyr_thigh_rps, kept), _cut(reuse.acc_thigh_mps2, kept)
        off1, gb1 = reuse.acc_offset_thigh_mps2, reuse.gyr_bias_thigh_rps
        gaps1, filled1 = reuse.thigh_gaps_s, reuse.thigh_filled_s
        br1, noted1 = reuse.bridged_gaps - reuse.shank_bridged, reuse.thigh_noted_s
    else:
        thigh6, gaps1, filled1, noted1, br1, off1, gb1 = _sensor_on_grid(t_grid, t1, g1, a1, fs1, fs_hz, params,
                                                                          posture)
        gyr_thigh, acc_thigh = thigh6[:, :3], thigh6[:, 3:]
    shank6, gaps2, filled2, noted2, br2, off2, gb2 = _sensor_on_grid(t_grid, t2, g2, a2, fs2, fs_hz, params, posture)
    gaps = sorted(gaps1 + gaps2)
    valid = ~_mask_intervals(t_grid, gaps)
    return PreparedLeg(
        leg=leg, fs_hz=fs_hz, t0_s=float(t_start), t_s=t_grid,
        gyr_thigh_rps=gyr_thigh, gyr_shank_rps=shank6[:, :3],
        acc_thigh_mps2=acc_thigh, acc_shank_mps2=shank6[:, 3:],
        valid=valid, saturated=saturated, gaps_s=merged_intervals(gaps), bridged_gaps=br1 + br2,
        bridged_s=merged_intervals(noted1 + noted2), filled_s=merged_intervals(filled1 + filled2),
        thigh_gaps_s=gaps1, thigh_filled_s=filled1, thigh_noted_s=noted1, shank_bridged=br2,
        thigh_saturated=sat_thigh, shank_saturated_raw=sat_shank,
        acc_offset_thigh_mps2=off1, acc_offset_shank_mps2=off2, gyr_bias_thigh_rps=gb1, gyr_bias_shank_rps=gb2,
    )


def _sensor_on_grid(t_grid: np.ndarray, t: np.ndarray, gyr: np.ndarray, acc: np.ndarray, fs: float, fs_hz: float,
                    params: PrepareParams, posture: PostureParams
                    ) -> tuple[np.ndarray, list[tuple[float, float]], list[tuple[float, float]],
                               list[tuple[float, float]], int, np.ndarray, np.ndarray]:
    """One sensor's SI stream ``(t, gyr, acc)`` (nominal rate ``fs``) on the grid: its (N, 6) channels with holes
    filled (:func:`periodic_fill`) and the rest offsets removed, its masked gaps, filled holes, holes left to the
    cubic that get a note, number of bridged holes, accelerometer offset and gyro bias."""
    gaps, n_bridged, noted = find_gaps(t, fs, params)
    masked = len(gaps)
    x, filled, gaps = periodic_fill(t_grid, _interp_columns(t_grid, t, _channels(gyr, acc), params.max_bridge_s),
                                    gaps, fs_hz, params, bridged=noted)
    n_bridged += masked - len(gaps)
    done = set(filled)
    noted = [g for g in noted if g not in done]
    off, gb = rest_offsets(x[:, 3:], x[:, :3], ~_mask_intervals(t_grid, gaps), fs_hz, posture)
    x -= np.concatenate((gb, off))  # this pass's own array: corrected in place
    return x, gaps, filled, noted, n_bridged, off, gb


def _kept_grid(reuse: PreparedLeg | None, t2: np.ndarray, fs_hz: float) -> slice | None:
    """The part of ``reuse``'s grid inside the re-stamped shank's span ``t2`` (a slice of it), None when there is
    no first pass to keep or too little of it is left. The clock correction moves the shank's stamps by a fraction
    of a sample to a few samples, and the thigh's channels on the first grid do not depend on the shank's clock, so
    the grid keeps its phase and only loses the samples at its ends that the shank no longer covers. Rebuilding it
    from the re-stamped span instead would shift its phase by the correction and interpolate the thigh once more,
    for no measurable difference in the accuracy tables (README, "Processing speed")."""
    if reuse is None or reuse.fs_hz != fs_hz:
        return None
    lo = int(np.searchsorted(reuse.t_s, t2[0], side="left"))
    hi = int(np.searchsorted(reuse.t_s, t2[-1], side="right"))
    if hi - lo < 2:
        return None
    return slice(None) if lo == 0 and hi == reuse.n else slice(lo, hi)


def _cut(x: np.ndarray, kept: slice) -> np.ndarray:
    """``x[kept]``, or ``x`` itself for the whole grid (the first pass's arrays, not new views of them)."""
    return x if kept == slice(None) else x[kept]
