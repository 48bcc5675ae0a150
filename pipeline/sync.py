"""Thigh/shank clock offset and drift of one leg, and the leg prepared again with the shank's stamps corrected.

Two constraints of Seel et al. 2014 carry the timing: the hinge (Eq. 2; :func:`pipeline.axes.sync_lag_estimate`)
and the joint centre (Eq. 5; :func:`pipeline.axes.estimate_centre_lag_s`). Neither holds on every knee. A real knee
is no hinge: the tibia turns about its long axis as the knee flexes and ab/adducts a few degrees, and the
gait-locked misfit reads as a lag (5-15 ms on the simulator's ``joint_3d`` axis; -10 / -18 ms on the
hardware-synchronised biomechZoo trial). Such a knee shows itself in the hinge fit, whose axes lean towards the
segments' long axes (``pipeline.axes.JointAxes.leaning``): its timing then comes from the joint centre. The
joint-centre constraint needs rigid segments, which a heel-strike shock ringing through the shank is not for
~0.1 s: those samples are left out (:func:`shock_mask`). Where the knee is a hinge, the hinge cue is the more precise
of the two and is used wherever it speaks (out-of-plane motion: turns, hip ab/adduction). A tibia that turns as the
knee flexes does not always make the hinge fit lean, so the joint-centre cue checks every hinge line: where the two
disagree by more than ``SyncParams.agree_s``, the joint centre's line is applied. Eq. 5 holds on any knee that turns
about a centre, a hinge or not, while the hinge cue reads a gait-locked axial rotation as a lag.

A 10-15 ms offset, common between two BLE sensors, would otherwise distort swing flexion by several degrees.

Two clocks also run at their own rates, so the lag drifts: one lag per window, a line through them (weighted by each
hinge window's standard error, so a window that lost its turns to packet loss weighs less). A window's lag is
that of the samples that carry the cue (turns for the hinge, heel strikes for the centre), so it is placed at their
weighted time, not at the window's middle (with 300 ppm the window lags then fit their line within ~1 ms, instead of
scattering by several); each window's search follows the line of the windows before it, so a lag that drifts out of
``SyncParams.max_lag_s`` is still found. A line steeper than two crystals drift apart (``SyncParams.max_drift``)
is applied only where the stride timing, a cue of its own (:func:`stride_timing_drift`), shows no drift left after
it: calibrated RC oscillators (+-250-500 ppm each) drift so, but a gyro bias's misfit in the hinge cue can move the
window lags so as well; without that second cue the leg's timing is unknown (``clock_disagreement``). A line
steeper than ``SyncParams.max_line_drift`` is beyond what the windows can see: no correction, and the leg's strides
are kept out of trends (``clock_disagreement``). A faster clock takes the lag out of the windows' search range before
they can follow it: where the stride timing shows such a drift, the shank is re-stamped by it first and the windows
read what is left. After all of this the stride timing checks the result (:func:`stride_clock_runaway`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import median_abs_deviation

from pipeline.axes import (
    JointAxes,
    LagEstimate,
    angular_acceleration,
    axis_up,
    estimate_centre_lag_s,
    fit_joint_axes,
    fit_margin_mask,
    hinge_rates,
    orient_thigh_on_gait,
    sync_lag_estimate,
)
from pipeline.constants import G_MPS2
from pipeline.params import WALKING, AxesParams, PipelineParams, SyncParams
from pipeline.prepare import SI, PreparedLeg, nominal_fs, prepare_leg_si, to_si
from pipeline.signal_utils import lowpass_runs_many, row_norm
from pipeline.types import RawSensorStream
from pipeline.walking import fit_gyros, gait_events, orient_on_gait, reusable_thigh_fit


@dataclass(frozen=True)
class SyncedLeg:
    """A prepared leg with its axes and the clock model applied to the shank (None when not applied)."""

    prep: PreparedLeg
    axes: JointAxes
    shank_lag_ms: float | None  # offset at mid-session
    shank_drift_ppm: float | None
    fit_gyr: tuple[np.ndarray, np.ndarray] | None  # :func:`pipeline.walking.fit_gyros` of ``prep`` when computed
    thigh_fit: np.ndarray | None = None  # else its thigh half when known (:func:`pipeline.walking.reusable_thigh_fit`)
    clock_disagreement: bool = False  # :attr:`ClockFit.disagreement`: the leg's thigh-shank timing is unknown


@dataclass(frozen=True)
class ClockFit:
    """The shank-vs-thigh clock model of one leg: ``lag(t) = offset_s + drift * (t - t_mid)``."""

    offset_s: float | None  # lag at mid-session [s]; None: no correction applied
    drift: float = 0.0  # [s/s]
    # the leg's timing is unknown: the window lags run apart faster than ``SyncParams.max_line_drift``, the wide
    # search's scatter far from zero, or the joint-centre check bears out neither cue (:func:`_checked_by_centre`)
    disagreement: bool = False
    # the joint-centre cue's line where it differs from this one (the hinge cue's) by more than ``agree_s`` at
    # mid-session: it is applied instead (:attr:`applied`)
    alternative: ClockFit | None = None

    @property
    def applied(self) -> ClockFit:
        """The line a leg is re-stamped by: the joint centre's where the cues disagree, else this one."""
        return self.alternative or self


def synchronised_leg(leg: str, thigh: RawSensorStream, shank: RawSensorStream, params: PipelineParams,
                     si: tuple[SI, SI] | None = None) -> SyncedLeg:
    """Prepare a leg, fit its axes, and when the hinge constraint shows a thigh/shank clock offset larger than
    ``SyncParams.min_shift_samples`` of a sample, prepare it again with the shank's time stamps corrected (the axes
    do not move with the lag); where the joint-centre cue disagrees with the hinge's line
    (:attr:`ClockFit.alternative`), by the joint centre's line. Where the window lags give no line the stride timing
    bears out, but the stride timing shows a drift no pair of crystals has, the shank is re-stamped by that drift
    and the windows tried again (:func:`_clock_after_stride_drift`). ``si``: both streams'
    :func:`pipeline.prepare.to_si` when the caller has them (never modified). Raises ValueError with less than a
    second of usable samples."""
    si1, si2 = (to_si(thigh), to_si(shank)) if si is None else si
    fs1 = nominal_fs(thigh, si1[0]) if si1[0].size else 0.0
    fs2 = nominal_fs(shank, si2[0]) if si2[0].size else 0.0
    prep = prepare_leg_si(leg, si1, si2, fs1, fs2, params=params.prepare, posture=params.posture)
    if prep.valid.sum() < max(10, int(prep.fs_hz)):
        raise ValueError("less than one second of usable samples")
    g1, g2 = fit_gyros(prep, params.axes.fit_cutoff_hz)
    axes = _fitted_axes(prep, g1, g2, params)
    streams = _LegStreams(leg, (si1, si2), (fs1, fs2), prep, (g1, g2))
    clock = clock_model(prep, g1, g2, axes, params.sync, params.axes)
    line = clock.applied
    synced = None if line.offset_s is None else _corrected(streams, axes, line.offset_s, line.drift, params)
    if synced is not None:
        return synced
    seen = _leg_stride_drift(prep, axes, params, (g1, g2))
    if seen is not None and seen.beyond(params.sync.max_drift):
        found = _clock_after_stride_drift(streams, seen.drift, params)
        synced = None if found is None else _corrected(streams, found[2], found[0], found[1], params)
        if synced is not None:
            return synced
    # no line, or one the stride timing does not bear out (then the leg's timing is unknown)
    return SyncedLeg(prep, axes, None, None, (g1, g2),
                     clock_disagreement=clock.disagreement or clock.offset_s is not None)


@dataclass(frozen=True)
class _LegStreams:
    """What re-stamping a leg's shank needs: its streams as :func:`pipeline.prepare.to_si` gave them, their nominal
    rates, the first preparation (its grid and thigh are kept) and its fit gyros (:func:`fit_gyros`)."""

    leg: str
    si: tuple[SI, SI]
    fs: tuple[float, float]
    prep: PreparedLeg
    fit_gyr: tuple[np.ndarray, np.ndarray]

    @property
    def t_mid(self) -> float:
        """The first preparation's middle [s], where a lag line's offset is given."""
        return float(self.prep.t_s[self.prep.n // 2])

    def restamped(self, offset: float, drift: float, params: PipelineParams) -> PreparedLeg:
        """The leg prepared again with the shank's stamps moved back by lag(t) = ``offset`` + ``drift`` *
        (t - :attr:`t_mid`) [s]: on the first grid, whose thigh is kept (:func:`pipeline.prepare.prepare_leg_si`)."""
        return prepare_leg_si(self.leg, *self.si, *self.fs, shank_shift_s=-(offset - drift * self.t_mid),
                              shank_drift=-drift, reuse=self.prep, params=params.prepare, posture=params.posture)


def _corrected(streams: _LegStreams, axes: JointAxes, offset: float, drift: float, params: PipelineParams
               ) -> SyncedLeg | None:
    """The leg with its shank's stamps corrected by lag(t) = ``offset`` + ``drift`` * (t - t_mid) [s]; the first
    preparation where the correction is below ``min_shift_samples`` of a sample; None for a line steeper than two
    crystals drift apart that the re-stamped leg's stride timing does not bear out (:func:`_stride_timing_agrees`)."""
    prep = streams.prep
    if max(abs(offset), abs(drift) * (prep.t_s[-1] - prep.t_s[0]) / 2) * prep.fs_hz <= params.sync.min_shift_samples:
        return SyncedLeg(prep, axes, round(1000 * offset, 1), round(1e6 * drift, 1), streams.fit_gyr)
    again = streams.restamped(offset, drift, params)
    if abs(drift) > params.sync.max_drift and not _stride_timing_agrees(again, axes, params):
        return None
    return SyncedLeg(again, axes, round(1000 * offset, 1), round(1e6 * drift, 1), None,
                     reusable_thigh_fit(prep, again, streams.fit_gyr[0]))


def clock_model(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                axes_params: AxesParams | None = None) -> ClockFit:
    """:func:`_clock_model` within ``max_lag_s``; where that finds no line, once more within ``wide_max_lag_s``. The
    narrow search first: over the wide range the cost curves of windows without a clear minimum near zero (jumps,
    sit-to-stand) find false ones, and the sweep's sessions with activities between walks came out worse for it. A
    lag beyond ``max_lag_s`` leaves every window's minimum at the edge of its range (no line), which the wide search
    then finds: phone-side stamps carry a BLE connection interval and the radio's buffering, and two independent
    simulators drew +-40 ms per sensor (80 ms between a thigh and its shank), whose 60-75 ms went uncorrected with
    swing peaks 10-40 deg off. A line to be applied (the joint centre's where the cues disagree) found near the edge
    of the narrow range (beyond ``wide_from_share`` of it: the windows' searches follow the line of those before and
    slide part of the way out) is searched wide as well, and the wide line kept where there is one (a drifting
    clock's narrow line lies there too, rightly). Where the wide search's windows scatter but all lie beyond
    ``scattered_max_lag_s`` on one side, the timing is unknown."""
    fit = _clock_model(prep, g1, g2, axes, params, axes_params)
    applied = fit.applied
    near_edge = applied.offset_s is not None and abs(applied.offset_s) > params.wide_from_share * params.max_lag_s
    if (fit.offset_s is not None and not near_edge) or fit.disagreement or params.wide_max_lag_s <= params.max_lag_s:
        return fit
    wide = _clock_model(prep, g1, g2, axes, dataclasses.replace(params, max_lag_s=params.wide_max_lag_s),
                        axes_params, wide=True)
    return fit if near_edge and wide.offset_s is None else wide


def _clock_model(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                 axes_params: AxesParams | None = None, wide: bool = False) -> ClockFit:
    """Shank-vs-thigh lag at mid-session [s] and its drift [s/s] (:func:`_line_model`): one lag per ``window_s``
    window, at least three windows, so that a drift shows as a slope and the windows can disagree with a line. The
    hinge constraint's lags where the knee moves as a hinge and they speak; the joint-centre constraint's (when
    ``axes_params`` is given) where the hinge's own fit leans towards the segments' long axes
    (``JointAxes.leaning``: the tibia turns as the knee flexes, and the gait-locked misfit reads as a lag) or where
    the hinge constraint is silent (straight walking, jumps: no out-of-plane motion). Hinge windows that speak but
    scatter mark a leg whose timing is not corrected. A leg shorter than two windows gets a constant lag from the
    joint-centre cue on its halves (:func:`_short_session_lag`). ``g1``, ``g2``: low-passed gyros (N, 3) [rad/s]."""
    fs = prep.fs_hz
    win = int(params.window_s * fs)
    if prep.n < 2 * win:
        return ClockFit(None if wide else _short_session_lag(prep, g1, g2, axes, params, axes_params))
    edges = np.linspace(0, prep.n, max(int(prep.n // win), 3) + 1).astype(int)
    windows = [slice(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    if not axes.leaning:
        h1, h2 = axes.hinge()
        rates = hinge_rates(g1, g2, h1, h2)  # once for all windows
        hinge: list[LagEstimate | None] = []
        fit_params = axes_params or WALKING.axes
        # a filled hole's timing is its neighbouring strides', not this leg's clocks', and the low-pass rings into
        # the samples next to any hole: at 10 % packet loss these had scattered the window lags by 10-20 ms
        measured = fit_margin_mask(prep.measured(), fs, fit_params)

        def hinge_lag(w: slice, centre_s: float) -> LagEstimate | None:
            hinge.append(sync_lag_estimate(g1, g2, h1, h2, measured, fs, window=w, rates=rates,
                                           max_lag_s=params.max_lag_s, centre_s=centre_s,
                                           cutoff_hz=fit_params.fit_cutoff_hz))
            return hinge[-1]
        # the cue's information on the lag: the squared slope of the compared rate (mostly in turns)
        weight = np.gradient(rates[1]) ** 2 * measured
        fit = _line_model(prep, windows, params, hinge_lag, weight=weight, wide=wide)
        # on a hinge knee the centre cue is the less accurate of the two wherever turns make both informative
        # (sweep and accuracy tune seeds: crouch gait, long lever arms); but a knee whose tibia turns as it flexes
        # without leaning the hinge fit reads a lag of its own into the hinge cue (10-25 ms on an independent
        # simulator), so the centre cue is asked too, from the hinge's line; where the two disagree the centre's line
        # is applied (:func:`synchronised_leg`)
        if fit.offset_s is not None and axes_params is not None:
            return _checked_by_centre(prep, g1, g2, axes, params, axes_params, windows, fit, wide)
        if fit.offset_s is not None or axes_params is None or sum(lag is not None for lag in hinge) >= 2:
            return fit
    elif axes_params is None:
        return ClockFit(None)
    return _centre_line(prep, windows, params, _centre_lag_of(prep, g1, g2, axes, params, axes_params), wide=wide)


def _checked_by_centre(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                       axes_params: AxesParams, windows: list[slice], fit: ClockFit, wide: bool = False) -> ClockFit:
    """The hinge cue's line ``fit``, with the joint-centre cue's line as its ``alternative`` where the two differ
    by more than ``agree_s``: first the middle window alone, searched around the hinge line; where it differs, the
    line on ``check_centre_windows`` windows, each searched from the middle window's lag (with the hinge's drift;
    its centres handed on from the first fit). Where the middle window has no clear minimum around a hinge line
    farther than ``agree_s`` from zero, it is searched around zero: a lag found there is the centre's probe where it
    lies beyond the range first searched or where a search from between the two finds it alone, else (a second
    valley near the hinge line) the timing is unknown. Where the middle window reads a lag beyond ``max_lag_s``, or
    where those windows make no line, or one that runs away faster than ``crystal_drift`` while the hinge's does
    not, and none of the other windows, searched from the hinge line, reads it, the two cues disagree and neither is
    borne out: the timing is unknown (``disagreement``)."""
    assert fit.offset_s is not None
    cue = _centre_lag_of(prep, g1, g2, axes, params, axes_params)
    mid, t_mid = windows[len(windows) // 2], float(prep.t_s[prep.n // 2])
    t_probe = _cue_time(prep, mid, cue[1])
    expected = fit.offset_s + fit.drift * (t_probe - t_mid)
    probe = cue[0](mid, expected)
    if probe is None and abs(expected) > params.agree_s:
        # no clear minimum within max_lag_s of a far hinge line: the centre cue is asked where clocks usually are
        probe = cue[0](mid, 0.0)
        if probe is not None and abs(probe.lag_s - expected) <= params.max_lag_s:
            # inside the range first searched, which showed no clear valley: either that range cut this valley at
            # its end, or it held a second one. Searched from between the two, one clear valley is this one
            between = cue[0](mid, 0.5 * (probe.lag_s + expected))
            if between is None or abs(between.lag_s - probe.lag_s) > params.agree_s:
                return ClockFit(None, disagreement=True)
    if probe is None or abs(probe.lag_s - expected) <= params.agree_s:
        return fit
    if abs(probe.lag_s) > params.max_lag_s:
        # the centre cue reads beyond the range searched: a line near its edge is searched wide (:func:`clock_model`)
        near_edge = not wide and abs(fit.offset_s) > params.wide_from_share * params.max_lag_s
        return ClockFit(None, disagreement=not near_edge)
    around = ClockFit(probe.lag_s - fit.drift * (t_probe - t_mid), fit.drift)
    alt = _centre_line(prep, windows, params, cue, around=around, max_windows=params.check_centre_windows, wide=wide)
    if alt.offset_s is None or abs(alt.drift) > params.crystal_drift >= abs(fit.drift):
        # the centre's windows make no line (they scatter, or too few speak), or one that runs away faster than two
        # crystals can where the hinge's does not (two windows 12 ms apart at 10 % packet loss: -390 ppm): the hinge
        # line stands where another of them, searched from it, reads it
        for w in _spread(windows, params.check_centre_windows):
            if w == mid:
                continue  # its lag does not depend on where it is searched from: read above
            on_line = fit.offset_s + fit.drift * (_cue_time(prep, w, cue[1]) - t_mid)
            est = cue[0](w, on_line)
            if est is not None and abs(est.lag_s - on_line) <= params.agree_s:
                return fit
        return ClockFit(None, disagreement=True)
    if abs(alt.offset_s - fit.offset_s) > params.agree_s:
        return ClockFit(fit.offset_s, fit.drift, alternative=alt)
    return fit


CentreCue = tuple[Callable[[slice, float], LagEstimate | None], np.ndarray]


def _centre_line(prep: PreparedLeg, windows: list[slice], params: SyncParams, cue: CentreCue,
                 around: ClockFit | None = None, max_windows: int | None = None, wide: bool = False) -> ClockFit:
    """The joint-centre cue's line (:func:`_line_model`; ``cue``: :func:`_centre_lag_of`) on at most
    ``max_windows`` (default ``max_centre_windows``) of ``windows``, spread evenly; with ``around``, each window
    searched around that line's lag at its time instead of the windows before it."""
    lag_of, weight = cue
    search = lag_of
    if around is not None and around.offset_s is not None:
        offset, drift, t_mid = around.offset_s, around.drift, float(prep.t_s[prep.n // 2])

        def search(w: slice, _predicted: float) -> LagEstimate | None:
            return lag_of(w, offset + drift * (_cue_time(prep, w, weight) - t_mid))
    count = params.max_centre_windows if max_windows is None else max_windows
    return _line_model(prep, _spread(windows, count), params, search, weight=weight, wide=wide)


def _spread(windows: list[slice], count: int) -> list[slice]:
    """At most ``count`` of ``windows``, spread evenly (the first and the last among them)."""
    pick = np.unique(np.linspace(0, len(windows) - 1, min(len(windows), count)).round())
    return [windows[int(i)] for i in pick]


def _cue_time(prep: PreparedLeg, w: slice, weight: np.ndarray | None) -> float:
    """Where in window ``w`` its lag is measured [s]: the ``weight``-ed mean time, else the window's middle."""
    if weight is not None and weight[w].sum() > 0:
        return float(np.average(prep.t_s[w], weights=weight[w]))
    return float(prep.t_s[(w.start + w.stop) // 2])


@dataclass(frozen=True)
class StrideDrift:
    """The shank's clock drift against the thigh's [s/s] that the stride timing shows and its 95 % interval, and
    the 95 % interval of the same slope within each walking run alone (``within_low``, ``within_high``)."""

    drift: float
    low: float
    high: float
    within_low: float = -np.inf
    within_high: float = np.inf

    def beyond(self, limit: float) -> bool:
        """Whether each interval lies wholly beyond ``+-limit`` [s/s]: a clock drifts within every walking run as
        well, while a change of gait between runs (another pace, pivoting steps, a thigh whose swing peak moves
        with the style of walking) shifts a run's lead as a whole (an independent simulator: 110 ms from one bout
        to the next, read as 900 ppm over the session, 22 of 80 legs flagged). Their signs may differ: a lead that
        runs past the search window around each mid-swing wraps the session's slope (5000 ppm read as -835)."""
        return (self.low > limit or self.high < -limit) and (self.within_low > limit or self.within_high < -limit)


def stride_timing_drift(t_s: np.ndarray, thigh_sag_dps: np.ndarray, ms: np.ndarray, fs_hz: float,
                        params: SyncParams) -> StrideDrift | None:
    """The shank's clock drift against the thigh's that the stride timing shows, None with too few strides (fewer
    than ``stride_cue_min_strides`` over ``stride_cue_min_span_s``). Each stride's thigh swing peak (the hip flexes
    fastest in early swing) leads the shank's mid-swing peak ``ms`` (indices) by a nearly constant share of the
    stride (SD ~8 ms on the simulator's 4-minute walks); a shank clock running ``drift`` fast delays the shank's
    peaks by ``drift * t`` more: the slope of that lead over the session beside the stride period
    (:func:`_drift_beside_pace`). A cue of its own, independent of the window lags: it needs neither a hinge nor a
    joint centre. ``thigh_sag_dps`` (N,) g1.j1 on the grid."""
    before, after = (int(round(x * fs_hz)) for x in params.stride_cue_window_s)
    ms = np.asarray(ms, dtype=int)
    if ms.size < max(params.stride_cue_min_strides, 2):
        return None
    # each stride's period: the shorter of the intervals to its neighbouring mid-swings (the other may span a pause)
    gaps = np.diff(t_s[ms])
    period = np.minimum(np.concatenate(([np.inf], gaps)), np.concatenate((gaps, [np.inf])))
    inside = (ms >= before) & (ms + after < t_s.shape[0])
    ms, period = ms[inside], period[inside]
    if ms.size < params.stride_cue_min_strides:
        return None
    seg = thigh_sag_dps[ms[:, None] + np.arange(-before, after + 1)]
    ok = np.isfinite(seg).all(axis=1)
    if ok.sum() < params.stride_cue_min_strides:
        return None
    t, period = t_s[ms[ok]], period[ok]
    if t.size < 2 or t[-1] - t[0] < params.stride_cue_min_span_s:
        return None
    peaks = seg[ok]
    k = np.argmax(peaks, axis=1)
    rows = np.arange(k.size)
    # the peak between samples (a parabola through its neighbours): at 100 Hz the lead moves by 10 ms steps, as
    # much as a 1000 ppm drift in 10 s
    y0, y1, y2 = (peaks[rows, np.clip(k + d, 0, peaks.shape[1] - 1)] for d in (-1, 0, 1))
    curv = y0 - 2 * y1 + y2
    inner = (k > 0) & (k < peaks.shape[1] - 1) & (curv < 0)
    frac = np.where(inner, 0.5 * (y0 - y2) / np.where(inner, curv, -1.0), 0.0)
    lead = (before - (k + frac)) / fs_hz
    # a lead read to a sample has the uniform quantisation error's SD at least (1 / fs / sqrt 12)
    floor = 1.0 / (fs_hz * np.sqrt(12.0))
    # walking runs: a pause longer than half a stride more than the stride's own period starts a new one
    run = np.concatenate(([0], np.cumsum(np.diff(t) > 1.5 * period[:-1])))
    whole = _drift_beside_pace(lead, t, period, np.zeros_like(run), floor)
    if not (whole.low > params.crystal_drift or whole.high < -params.crystal_drift):
        return whole  # beyond no limit the checks use (crystal_drift the least): the runs' slopes cannot add a claim
    within = _drift_beside_pace(lead, t, period, run, floor)
    return StrideDrift(whole.drift, whole.low, whole.high, within.low, within.high)


def _drift_beside_pace(lead_s: np.ndarray, t_s: np.ndarray, period_s: np.ndarray, run: np.ndarray, floor_s: float
                       ) -> StrideDrift:
    """The drift [s/s] of the thigh's lead over the session, with the stride period as a second regressor: the thigh
    leads the shank by a share of the stride, so a slow bout after a brisk one lengthens the lead by tens of ms
    (brisk 1.5 m/s then 0.4 m/s: 1000-1200 ppm read as a drift on an independent simulator, both legs flagged), while
    a clock drift adds to it in proportion to time whatever the pace. Huber's M-estimator (k = 1.345, scale the
    residuals' MAD) by iteratively reweighted least squares, and the 95 % interval of the drift from its weighted
    covariance. Where the pace changes steadily over the session the two regressors overlap and the interval
    widens: no drift is then claimed. ``run`` (one label per stride): each run gets an intercept of its own, so only
    the slopes within runs measure the drift (all one label: the session's slope). ``floor_s``: the smallest residual
    scale (a lead read to a fraction of a sample is no more exact than that, whatever the residuals' MAD says)."""
    group = np.unique(run, return_inverse=True)[1]

    def within(v: np.ndarray, w: np.ndarray) -> np.ndarray:
        # each run's weighted mean removed: the runs' intercepts profiled out (Frisch-Waugh-Lovell), so the cost
        # stays linear in the strides however many runs there are
        return v - (np.bincount(group, w * v) / np.bincount(group, w))[group]

    w = np.ones_like(t_s)
    scale = 0.0
    for _ in range(20):
        x = np.column_stack([within(period_s, w), within(t_s, w)])
        y = within(lead_s, w)
        beta = np.linalg.lstsq(x * np.sqrt(w)[:, None], y * np.sqrt(w), rcond=None)[0]
        r = y - x @ beta
        scale = max(float(median_abs_deviation(r, scale="normal")), floor_s)
        u = np.abs(r) / (1.345 * scale)
        w_new = np.where(u <= 1.0, 1.0, 1.0 / np.maximum(u, 1e-12))
        if np.allclose(w_new, w, atol=1e-6):
            break
        w = w_new
    x = np.column_stack([within(period_s, w), within(t_s, w)])
    xtwx = (x * w[:, None]).T @ x
    se = scale * float(np.sqrt(max(np.linalg.pinv(xtwx)[-1, -1], 0.0)))
    drift = float(beta[-1])
    return StrideDrift(drift, drift - 1.96 * se, drift + 1.96 * se)


def stride_clock_runaway(t_s: np.ndarray, thigh_sag_dps: np.ndarray, ms: np.ndarray, fs_hz: float,
                         params: SyncParams, limit: float | None = None) -> bool:
    """Whether the stride timing (:func:`stride_timing_drift`) shows the shank's clock running away from the
    thigh's faster than ``limit`` [s/s] (default ``max_drift``) after the clock model: a check the window lags
    cannot make once a drift smears a window's lag beyond the search range (beyond ~1000 ppm in 40 s windows), nor
    after a wrong correction. True when the 95 % interval lies wholly beyond ``limit``."""
    seen = stride_timing_drift(t_s, thigh_sag_dps, ms, fs_hz, params)
    return seen is not None and bool(seen.beyond(params.max_drift if limit is None else limit))


def _leg_stride_drift(prep: PreparedLeg, axes: JointAxes, params: PipelineParams,
                      fit_gyr: tuple[np.ndarray, np.ndarray] | None = None) -> StrideDrift | None:
    """:func:`stride_timing_drift` of a prepared leg: the gait events on its shank (:func:`gait_events`) and its
    thigh's sagittal rate, the axis's sign taken from gait. ``fit_gyr``: :func:`fit_gyros` of ``prep`` if known."""
    g1, g2 = fit_gyros(prep, params.axes.fit_cutoff_hz) if fit_gyr is None else fit_gyr
    _, ev = gait_events(prep, axes, params)
    j1 = orient_thigh_on_gait(axes.j1, axes.j2, g1, g2, list(ev.strides), prep.fs_hz)
    thigh_sag = np.rad2deg(prep.gyr_thigh_rps @ j1)
    thigh_sag[~prep.valid] = np.nan
    return stride_timing_drift(prep.t_s, thigh_sag, ev.ms[(ev.ms >= 0) & (ev.bout >= 0)], prep.fs_hz, params.sync)


def _stride_timing_agrees(prep: PreparedLeg, axes: JointAxes, params: PipelineParams) -> bool:
    """Whether the stride timing (:func:`stride_timing_drift`) of a leg whose shank was re-stamped by a line no pair
    of crystals explains (beyond ``max_drift``) shows no drift left: its 95 % interval, widened by a line that moves
    the lag by ``agree_s`` at the session's ends, holds zero. The window lags alone are not enough for such a line:
    a gyro bias that drifts over the session moves the hinge cue's misfit, and its lags follow a line of their own;
    and their search follows at most ``max_drift`` from window to window, so a faster clock's line can come out too
    flat. Checked on the re-stamped leg, where what is left of the drift stays within the stride cue's window
    (a whole drift of 1000 ppm moves the stride timing by 0.3 s over 5 minutes). Without that agreement the leg's
    timing is unknown (``clock_disagreement``), as for any line the windows alone show."""
    seen = _leg_stride_drift(prep, axes, params)
    if seen is None:
        return False
    tol = 2 * params.sync.agree_s / float(prep.t_s[-1] - prep.t_s[0])
    return seen.low - tol <= 0.0 <= seen.high + tol


def _clock_after_stride_drift(streams: _LegStreams, drift: float, params: PipelineParams
                              ) -> tuple[float, float, JointAxes] | None:
    """The clock line (offset at :attr:`_LegStreams.t_mid` [s], drift [s/s]) and joint axes of a leg where the
    stride timing shows a drift ``drift`` [s/s] beyond ``max_drift`` and the window lags gave no line it bears out:
    a lag that runs away so fast leaves the windows' search range before they can follow it, and it blurs the axis
    fit's own lag. The shank is re-stamped by ``drift`` first and the axes fitted again on it. The stride timing
    tells a drift, not an offset, and what is left is a lag as large as the drift made it somewhere (two clocks
    started together are 0.1 s apart at the middle of a 5-minute session at 600 ppm): the hinge cue finds it on the
    whole re-stamped leg at once, over as wide a range (up to ``SyncParams.restamp_max_lag_s``), and the shank is
    re-stamped by it too. The windows then see only what is left (a crystal's worth); the lines add. None where the
    windows see no line there, or a steeper one than two crystals give."""
    prep = streams.prep
    cutoff = params.axes.fit_cutoff_hz

    def restamped(offset: float) -> tuple[PreparedLeg, np.ndarray, np.ndarray, JointAxes]:
        again = streams.restamped(offset, drift, params)
        h1, h2 = fit_gyros(again, cutoff)
        return again, h1, h2, _fitted_axes(again, h1, h2, params)

    again, h1, h2, axes = restamped(0.0)
    offset = 0.0
    if not axes.leaning:
        wide = min(abs(drift) * float(prep.t_s[-1] - prep.t_s[0]) / 2 + params.sync.max_lag_s,
                   params.sync.restamp_max_lag_s)
        whole = sync_lag_estimate(h1, h2, *axes.hinge(), fit_margin_mask(again.measured(), again.fs_hz, params.axes),
                                  again.fs_hz, max_lag_s=wide, cutoff_hz=cutoff)
        if whole is not None and abs(whole.lag_s) > params.sync.max_lag_s / 2:
            offset = whole.lag_s  # beyond half the windows' range: their first search would miss it
            again, h1, h2, axes = restamped(offset)
    rest = clock_model(again, h1, h2, axes, params.sync, params.axes)
    rest = rest.applied
    if rest.offset_s is None or abs(rest.drift) > params.sync.max_drift:
        return None  # no line, or a steep one where only a crystal's worth of drift is left: the cues disagree
    # the rest's line at the first grid's middle (the re-stamped grid may be cut, which moves its own)
    t_mid_again = float(again.t_s[again.n // 2])
    return offset + rest.offset_s + rest.drift * (streams.t_mid - t_mid_again), drift + rest.drift, axes


def _fitted_axes(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, params: PipelineParams) -> JointAxes:
    """The joint axes of a prepared leg (:func:`pipeline.axes.fit_joint_axes`) on its measured samples (a fill
    repeats the neighbouring strides, and their timing would enter the fitted lag), their common sign from gait
    (:func:`pipeline.walking.orient_on_gait`)."""
    axes = fit_joint_axes(g1, g2, prep.measured(), params.axes, up=axis_up(prep, params.axes),
                          gd2_rps2=angular_acceleration(g2, prep.fs_hz) if params.axes.fit_lag else None)
    return orient_on_gait(prep, axes, g1, g2, params)


def _short_session_lag(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                       axes_params: AxesParams | None) -> float | None:
    """Constant lag [s] of a leg too short for two ``window_s`` windows (a 10 m walk test, a 30-60 s trial): the
    joint-centre cue (Seel Eq. 5) on its two halves, applied only when both are informative and agree within
    ``agree_s`` (the rule of :func:`_line_model`) and their lag exceeds ``short_min_lag_s``; halves shorter than
    ``short_window_s`` give no estimate. Not the hinge cue (Eq. 2): on the hardware-synchronised biomechZoo trial
    (10 s) it reads a false -10 / -18 ms and follows only a quarter of an imposed offset, where the centre cue
    follows it one to one. Two halves fix no drift: over such a session two crystals (up to ~200 ppm apart) move the
    lag by 6 ms at most."""
    half = prep.n // 2
    if axes_params is None or half < params.short_window_s * prep.fs_hz:
        return None
    halves = [slice(0, half), slice(half, prep.n)]
    lag = _line_model(prep, halves, params, _centre_lag_of(prep, g1, g2, axes, params, axes_params)[0],
                      drifting=False).offset_s
    return lag if lag is not None and params.short_min_lag_s < abs(lag) <= params.max_lag_s else None


def _centre_lag_of(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, axes: JointAxes, params: SyncParams,
                   axes_params: AxesParams) -> CentreCue:
    """The joint-centre lag of one window (:func:`pipeline.axes.estimate_centre_lag_s`), its inputs prepared once,
    and where in a window that lag is measured: (N,) the squared slope of the shank's acceleration on the fitted
    samples (the knee-centre acceleration changes most sharply at heel strike)."""
    fs = prep.fs_hz
    a1, a2, gd1, gd2, far = _centre_inputs(prep, g1, g2, params, axes_params)
    # the first window that fits centres hands them on: the others start from them (no restarts)
    centres: list[np.ndarray] = []

    def lag_of(w: slice, centre_s: float) -> LagEstimate | None:
        lag, fitted = estimate_centre_lag_s(a1, g1, gd1, a2, g2, gd2, axes.j1, axes.j2, far, fs, w,
                                            params.max_lag_s, axes_params, centres[0] if centres else None,
                                            centre_s, params.centre_depth, params.centre_lag_step_s)
        if fitted is not None and not centres:
            centres.append(fitted)
        return None if lag is None else LagEstimate(lag)
    return lag_of, row_norm(np.gradient(a2, axis=0)) ** 2 * far


def _centre_inputs(prep: PreparedLeg, g1: np.ndarray, g2: np.ndarray, params: SyncParams, axes_params: AxesParams
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What Seel's Eq. 5 is evaluated on for a leg: both accelerations low-passed at ``fit_cutoff_hz`` (NaN-free,
    (N, 3) [m/s^2]), the Eq. 1 angular accelerations of the fit gyros ``g1``, ``g2``, and the usable samples (N,):
    away from gaps and outside shocks (:func:`shock_mask`)."""
    fs = prep.fs_hz
    a1, a2 = (np.nan_to_num(a) for a in lowpass_runs_many((prep.acc_thigh_mps2, prep.acc_shank_mps2), prep.valid,
                                                            axes_params.fit_cutoff_hz, fs))
    gd1, gd2 = angular_acceleration(g1, fs), angular_acceleration(g2, fs)
    far = fit_margin_mask(prep.valid, fs, axes_params)
    far &= ~shock_mask(((prep.acc_thigh_mps2, a1), (prep.acc_shank_mps2, a2)), prep.valid, fs, params)
    return a1, a2, gd1, gd2, far


def shock_mask(acc: tuple[tuple[np.ndarray, np.ndarray], ...], valid: np.ndarray, fs_hz: float,
               params: SyncParams) -> np.ndarray:
    """(N,) bool: within ``shock_s`` of a sample where a segment's acceleration departs from its low-passed self
    (``acc``: pairs of raw and low-passed (N, 3) [m/s^2]) by more than ``shock_g``: a heel-strike or landing shock,
    ringing above the gait band, during which the two accelerometers do not measure one rigid knee-centre
    acceleration (Seel Eq. 5)."""
    shock = np.zeros(valid.shape[0], dtype=bool)
    for raw, low in acc:
        shock |= row_norm(np.nan_to_num(raw) - low) > params.shock_g * G_MPS2
    shock &= valid
    if not shock.any():
        return shock
    half = int(np.ceil(params.shock_s * fs_hz))
    return np.convolve(shock.astype(float), np.ones(2 * half + 1), mode="same") > 0


def _predicted_lag(pts: list[tuple[float, float]], t: float, params: SyncParams) -> float:
    """The lag [s] at time ``t`` that the (time, lag) points so far predict: none 0, one its lag, more their line
    (rate clipped to ``max_drift``: searching along a steeper prediction lets the windows follow the misfit of a
    gyro bias that drifts over the session; a steeper clock is still found where its lags stay in the search range)."""
    if len(pts) < 2:
        return pts[0][1] if pts else 0.0
    tt, lag = np.array(pts).T
    drift = float(np.clip(np.polyfit(tt, lag, 1)[0], -params.max_drift, params.max_drift))
    return float(np.median(lag - drift * tt) + drift * t)


def _window_lag(lag_of: Callable[[slice, float], LagEstimate | None], w: slice, centre: float, params: SyncParams,
                wide: bool) -> LagEstimate | None:
    """``lag_of(w, centre)``; in the wide search None unless clear (``wide_max_se_s``: over the wide range a
    shallow curve finds false minima)."""
    est = lag_of(w, centre)
    return None if wide and est is not None and est.se_s is not None and est.se_s > params.wide_max_se_s else est


def _line_model(prep: PreparedLeg, windows: list[slice], params: SyncParams,
                lag_of: Callable[[slice, float], LagEstimate | None], drifting: bool = True,
                weight: np.ndarray | None = None, wide: bool = False) -> ClockFit:
    """Offset at mid-session and drift of the window lags ``lag_of(window, centre_s)``, each searched around the
    lag the windows before it predict (``centre_s``: their line, clipped to ``max_drift``, at the window's time, so
    that a drifting lag is followed beyond ``max_lag_s``); no correction unless at least two
    windows are informative and all agree with the line within ``agree_s``; a disagreement where they agree on a
    line steeper than ``max_line_drift``.
    ``drifting``: the windows are long apart, so two informative ones that differ by more than ``agree_s`` give the
    drift between them (else the halves of a short session: a constant offset). ``weight``: (N,) where in each
    window its lag is measured (the window is placed at the weighted mean time, not at its centre: under a drift a
    window's lag is that of its turns or heel strikes). Where every lag carries a standard error the line is a
    weighted least-squares fit (weights 1 / max(se, ``window_lag_floor_s``)^2): a window that lost most of its
    turns to packet loss or speaks only faintly no longer sets the drift as much as the others. ``wide``: the search
    over ``wide_max_lag_s`` (:func:`clock_model`): only clear windows (standard error within ``wide_max_se_s``),
    ``wide_min_windows`` of them, a line no steeper than ``max_drift``; scattered windows about a far lag mark the
    timing unknown."""
    t_mid = float(prep.t_s[prep.n // 2])
    pts: list[tuple[float, float]] = []
    ses: list[float | None] = []
    for w in windows:
        t_w = _cue_time(prep, w, weight)
        est = _window_lag(lag_of, w, _predicted_lag(pts, t_w - t_mid, params) if drifting else 0.0, params, wide)
        if est is not None:
            pts.append((t_w - t_mid, est.lag_s))
            ses.append(est.se_s)
    if len(pts) < (params.wide_min_windows if wide else 2):
        return ClockFit(None)
    t, lag = np.array(pts).T
    inv_se = None
    if all(se is not None for se in ses):
        inv_se = 1.0 / np.maximum(np.array(ses, dtype=float), params.window_lag_floor_s)
    if len(pts) >= 3:
        drift = float(np.polyfit(t, lag, 1, w=inv_se)[0])
    elif drifting and abs(lag[1] - lag[0]) > params.agree_s:
        # a line through two points cannot disagree with them: their slope is taken only where a constant cannot
        # explain them (a difference beyond the window noise)
        drift = float((lag[1] - lag[0]) / (t[1] - t[0]))
    else:
        drift = 0.0
    offset = float(np.median(lag - drift * t) if inv_se is None else np.average(lag - drift * t, weights=inv_se ** 2))
    if np.max(np.abs(lag - offset - drift * t)) > params.agree_s:
        # scattered windows (a noisy cue), no clock seen: nothing corrected; but where the wide search puts every one
        # of them far from zero on the same side, the timing is known to be off by more than the strides can bear
        return ClockFit(None, disagreement=wide and bool(np.all(lag * np.sign(offset) > params.scattered_max_lag_s)))
    if wide and abs(drift) > params.max_drift:
        return ClockFit(None)  # the wide search is for an offset; a runaway clock is the re-stamping's (above)
    if abs(drift) > params.max_line_drift:
        # the windows agree on a lag that runs away faster than they can see: timing unknown
        return ClockFit(None, disagreement=True)
    return ClockFit(offset, drift)
