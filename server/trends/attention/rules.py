"""The attention flags as pure functions of a patient's evidence (no database: every rule is checked by hand in tests).

Methods (the ``rules`` block of the response says the same with the thresholds used):

- ``declining`` / ``improving``: ordinary least squares slope b of the session means of the assessed leg over the
  trend window (the last ``2 * window_days``), one-sided t-test of H0: b = 0 against a change in the worse (better)
  direction at level ``alpha`` (t = b / se(b); Montgomery & Runger, Applied Statistics, eq. 11-21/11-22),
  AND the fitted change over the data's span, b * span, beyond the MDC (Allseits et al. 2018 after Wilken et al.
  2012: 5 deg). se(b) is moderated (Smyth 2004, :func:`moderated`): the patient's residual variance on n - 2 df is
  pooled with the pipeline's known session-to-session scatter (``SESSION_SD_PRIOR``) weighted as ``sd_prior_df``
  df, and t has n - 2 + ``sd_prior_df`` df. The test alone would flag clinically trivial drifts of very regular
  patients, the MDC alone would flag noise; both together bound the false-alarm rate by ``alpha`` under i.i.d.
  session means, and the measured rate on simulated stable patients is in the README.
- ``stalled``: equivalence of the slope with zero by two one-sided tests (Schuirmann 1987, J Pharmacokinet
  Biopharm 15:657; Wellek, Testing Statistical Hypotheses of Equivalence and Noninferiority, 2nd ed. 2010, ch. 2)
  on the patient's own scatter (a plateau is claimed only from the patient's own data, never from the pooled
  variance the decline test uses): over the last ``stalled_weeks`` weeks, after >= ``stalled_min_sessions``
  sessions spanning >= ``stalled_min_span_days``, both one-sided ``stalled_confidence`` bounds of the slope,
  b +- t(conf, df) se(b), lie inside +-MDC per ``stalled_margin_days`` (the patient would show no detectable gain
  or loss from one 14-day comparison window to the next), the latest level is below the metric's goal, and the
  improvement is not significant. A margin of +-MDC per 4 weeks is out of reach with twice-weekly sessions whose
  means scatter by 2-3 deg (the 90 % CI alone is +-1.1 deg/week wide).
- ``silent``: no session for longer than ``silent_missed_sessions`` prescribed intervals (7 / prescribed sessions per
  week) when a schedule is set, else ``silent_days``.
- ``sensor_trouble``: data that cost strides or quality, never a count of gaps: per leg over the sensor window,
  after ``min_strides_for_rates`` expected strides, the share of strides lost (the other leg gave them), of low
  quality (saturation, drift, ...), from the fallback estimator, or with an impossible angle; per session, a
  sensor that delivered data for less than ``min_coverage`` of the session and cost >= ``min_lost_strides``; more
  than ``max_failed_sessions`` failed processing runs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import datetime, timedelta
from typing import Any

from scipy.special import stdtr

from server.numbers import finite_round
from server.trends import stats
from server.trends.attention.params import SESSION_SD_PRIOR, AttentionParams
from server.trends.metrics import Metric
from server.utc import as_utc

SEVERITY = {"declining": 3, "sensor_trouble": 2, "silent": 2, "stalled": 1, "improving": 0}


@dataclass(frozen=True)
class SessionLegEvidence:
    """What one session said about one leg's sensors (all activities)."""

    started_at: datetime
    leg: str
    n_strides: int
    n_expected: int
    n_low_quality: int
    n_fallback: int
    n_implausible: int
    n_gaps: int
    walking_s: float
    coverage: float | None


@dataclass(frozen=True)
class SlopeTest:
    """OLS slope of session means against time (days before now) with what the flags need."""

    n: int
    span_days: float
    slope_per_day: float
    intercept: float  # the fitted value now (time is measured from now)
    se: float | None
    df: int
    sxx: float = 0.0  # sum of squared time deviations (days^2): se = residual sd / sqrt(sxx)

    @property
    def fitted_change(self) -> float:
        """The change the line implies over the data's span."""
        return self.slope_per_day * self.span_days

    def t_stat(self) -> float:
        """b / se(b), +-inf for a perfect non-flat fit."""
        if self.se is None:
            return 0.0
        if self.se == 0.0:
            return math.copysign(math.inf, self.slope_per_day) if self.slope_per_day else 0.0
        return self.slope_per_day / self.se

    def ci(self, level: float) -> tuple[float, float] | None:
        """Two-sided ``level`` CI of the slope per day."""
        if self.se is None:
            return None
        half = stats.t_quantile(self.df, 0.5 + level / 2.0) * self.se
        return self.slope_per_day - half, self.slope_per_day + half


def slope_test(points: Sequence[stats.Point]) -> SlopeTest | None:
    """The OLS fit of session means on time, None with fewer than three points or all at one time."""
    if len(points) < 3:
        return None
    t = [pt.t_days for pt in points]
    fit = stats.ols_fit(t, [pt.mean for pt in points])
    if fit is None:
        return None
    b, a, se = fit
    tm = sum(t) / len(t)
    return SlopeTest(len(points), max(t) - min(t), b, a, se, len(points) - 2, sum((x - tm) ** 2 for x in t))


def moderated(fit: SlopeTest, prior_sd: float | None, prior_df: int) -> SlopeTest:
    """The slope test with its residual variance shrunk towards a prior (the moderated t of Smyth 2004, Stat Appl
    Genet Mol Biol 3(1):3, eq. 3-4): s~^2 = (d0 s0^2 + d s^2) / (d0 + d) on d0 + d degrees of freedom. Eight
    session means give a residual sd on 6 df, so uncertain that the t-test needs t > 3.14 at 1 %; the pipeline's
    session-to-session scatter is known much better than that from many patients."""
    if fit.se is None or prior_sd is None or prior_df <= 0 or fit.sxx <= 0.0:
        return fit
    s2 = fit.se * fit.se * fit.sxx
    s2_mod = (prior_df * prior_sd * prior_sd + fit.df * s2) / (prior_df + fit.df)
    return replace(fit, se=math.sqrt(s2_mod / fit.sxx), df=fit.df + prior_df)


def _sign(metric: Metric) -> int:
    return 1 if metric.better == "higher" else -1


def _windows(points: Sequence[stats.Point], window_days: float, start_days: float) -> tuple[stats.Window,
                                                                                         stats.Window]:
    base = [pt for pt in points if pt.t_days < -window_days]
    late = [pt for pt in points if pt.t_days >= -window_days]
    return (stats.window_summary(base, start_days, -window_days), stats.window_summary(late, -window_days, 0.0))


def _mdc(metric: Metric, level: float | None) -> float:
    return metric.mdc * abs(level or 0.0) if metric.mdc_relative else metric.mdc


def _trend_fields(fit: SlopeTest, p_one_sided: float) -> dict[str, Any]:
    ci = fit.ci(0.95)
    return {"slope_per_week": finite_round(7.0 * fit.slope_per_day, 3),
            "ci95_per_week": None if ci is None else [finite_round(7.0 * ci[0], 3), finite_round(7.0 * ci[1], 3)],
            "p_value": finite_round(p_one_sided, 6), "n_sessions": fit.n, "span_days": finite_round(fit.span_days, 1),
            "fitted_change": finite_round(fit.fitted_change, 3)}


def _one_sided_p(fit: SlopeTest, direction: int) -> float:
    t = direction * fit.t_stat()
    # stdtr is the t CDF as a plain ufunc (microseconds; scipy.stats' sf costs ~1 ms of argument handling).
    return float(stdtr(fit.df, -t)) if math.isfinite(t) else (0.0 if t > 0 else 1.0)


# An absolute knee angle rests on each session's absolute reference (an assumed or measured standing flexion and
# the accelerometer's inclination, Seel et al. 2014; Allseits et al. 2018 Sect. 2.4), which moves by a few degrees
# from session to session; the stride's excursion does not. Its significance is therefore tested on the excursion
# of the same strides (ROM = peak swing flexion - minimum flexion), which carries the same gain in knee motion
# without that offset, while the size of the change (fitted change vs MDC) is judged on the metric itself.
LEVEL_FREE_COMPANION: dict[str, str] = {"peak_swing_flexion_deg": "rom_deg"}


def change_flag(kind: str, p: AttentionParams, metric: Metric, leg: str, points: Sequence[stats.Point],
                test_points: Sequence[stats.Point] | None = None,
                test_metric: str | None = None) -> dict[str, Any] | None:
    """``declining`` or ``improving`` of one leg from its session points of the trend window (t in days, <= 0).

    ``test_points`` (of ``test_metric``, the same sessions): the series the slope's significance is tested on
    (see :data:`LEVEL_FREE_COMPANION`); default the metric's own points."""
    if metric.better == "none" or len(points) < max(p.min_trend_sessions, 3):
        return None
    fit = slope_test(points)
    if fit is None or fit.se is None or fit.span_days < p.min_trend_span_days:
        return None
    tested = fit
    if test_points is not None and len(test_points) >= max(p.min_trend_sessions, 3):
        tested = slope_test(test_points) or fit
    else:
        test_metric = None
    tested = moderated(tested, SESSION_SD_PRIOR.get(test_metric or metric.name), p.sd_prior_df)
    if tested.se is None:
        return None
    direction = -_sign(metric) if kind == "declining" else _sign(metric)  # the slope sign the flag looks for
    base, late = _windows(points, p.window_days, -2.0 * p.window_days)
    mdc = _mdc(metric, base.mean if base.mean is not None else late.mean)
    crit = stats.t_quantile(tested.df, 1.0 - p.alpha)
    if not (direction * tested.t_stat() > crit and direction * fit.fitted_change >= mdc):
        return None
    pval = _one_sided_p(tested, direction)
    delta = None if base.mean is None or late.mean is None else late.mean - base.mean
    change = fit.fitted_change
    verb = "fell" if change < 0 else "rose"
    tested_on = (f"{test_metric} {7.0 * tested.slope_per_day:+.1f} {metric.unit}/week, " if test_metric else "")
    return {"kind": kind, "leg": leg, "metric": metric.name, "delta": finite_round(delta, 3),
            "mdc": finite_round(mdc, 3), "baseline": base, "latest": late, **_trend_fields(fit, pval),
            "tested_on": test_metric or metric.name,
            "tested_slope_per_week": finite_round(7.0 * tested.slope_per_day, 3),
            "effect": finite_round(abs(change) / mdc if mdc else math.inf, 3),
            "reason": (f"{metric.name} of the {leg} leg {verb} by {abs(change):.1f} {metric.unit} over "
                       f"{fit.span_days:.0f} days ({7.0 * fit.slope_per_day:+.1f} {metric.unit}/week; "
                       f"{tested_on}one-sided p = {pval:.2g}, {fit.n} sessions; MDC {mdc:g})")}


def stalled_flag(p: AttentionParams, metric: Metric, leg: str, points: Sequence[stats.Point],
                 test_points: Sequence[stats.Point] | None = None,
                 test_metric: str | None = None) -> dict[str, Any] | None:
    """``stalled``: a plateau below the goal, shown by an equivalence test of the slope (points of the last
    ``stalled_weeks`` weeks; the slope from ``test_points``, the level-free companion, when given)."""
    goal = p.goal()
    if goal is None or metric.better == "none" or len(points) < max(p.min_trend_sessions, p.stalled_min_sessions, 3):
        return None
    companion = bool(test_points) and len(test_points or []) == len(points)
    fit = slope_test(test_points if companion and test_points else points)
    if fit is None or fit.se is None or fit.span_days < p.stalled_min_span_days:
        return None
    _, late = _windows(points, p.window_days, -7.0 * p.stalled_weeks)
    level = late.mean
    mdc = _mdc(metric, level)
    bound = mdc / p.stalled_margin_days  # per day
    s = _sign(metric)
    # One-sided confidence bounds of the gain per day (in the better direction): both inside +-bound.
    half = stats.t_quantile(fit.df, p.stalled_confidence) * fit.se
    upper, lower = s * fit.slope_per_day + half, s * fit.slope_per_day - half
    if level is None or upper >= bound or lower <= -bound or s * (goal - level) <= 0:
        return None
    if s * fit.t_stat() > stats.t_quantile(fit.df, 1.0 - p.alpha):
        return None  # a significant improvement is never a plateau
    conf = f"{100 * p.stalled_confidence:g} %"
    return {"kind": "stalled", "leg": leg, "metric": metric.name, "weeks": p.stalled_weeks,
            "delta": finite_round(fit.fitted_change, 3), "mdc": finite_round(mdc, 3), "goal": goal,
            "level": finite_round(level, 3), "latest": late, **_trend_fields(fit, _one_sided_p(fit, s)),
            "tested_on": (test_metric or metric.name) if companion else metric.name,
            "gain_bounds_per_week": [finite_round(7.0 * lower, 3), finite_round(7.0 * upper, 3)],
            "margin_per_week": finite_round(7.0 * bound, 3),
            "effect": finite_round(abs(goal - level) / mdc if mdc else 0.0, 3),
            "reason": (f"{metric.name} of the {leg} leg has plateaued at {level:.1f} {metric.unit}, "
                       f"{abs(goal - level):.1f} short of the goal {goal:g}: over {fit.span_days:.0f} days "
                       f"({fit.n} sessions{f', slope of {test_metric}' if companion and test_metric else ''}) it gains "
                       f"{7.0 * s * fit.slope_per_day:+.2f} {metric.unit}/week ({conf} bounds {7.0 * lower:+.2f} to "
                       f"{7.0 * upper:+.2f}), inside +-MDC {mdc:g} per {p.stalled_margin_days:g} days "
                       f"(+-{7.0 * bound:.2f}/week)")}


def silent_flag(p: AttentionParams, now: datetime, last: datetime | None, created: datetime,
                prescribed_per_week: float | None) -> dict[str, Any] | None:
    """``silent``: longer without a session than the schedule allows."""
    quiet_since = last if last is not None else created
    quiet_days = (now - as_utc(quiet_since)).total_seconds() / 86400.0
    if prescribed_per_week:
        limit = p.silent_missed_sessions * 7.0 / prescribed_per_week
        basis = (f"{prescribed_per_week:g} sessions/week prescribed: {p.silent_missed_sessions:g} sessions missed "
                 f"after {limit:.1f} days")
    else:
        limit, basis = p.silent_days, f"no schedule set: limit {p.silent_days:g} days"
    if quiet_days < limit:
        return None
    what = f"no session for {quiet_days:.1f} days" if last else f"no session since enrolment {quiet_days:.1f} days ago"
    return {"kind": "silent", "days_without_data": finite_round(quiet_days, 1),
            "last_session_at": as_utc(last).isoformat() if last else None, "limit_days": finite_round(limit, 2),
            "prescribed_sessions_per_week": prescribed_per_week, "effect": finite_round(quiet_days / limit, 3),
            "reason": f"{what} ({basis})"}


def _stopped_sensors(p: AttentionParams, rows: Sequence[SessionLegEvidence]) -> list[tuple[SessionLegEvidence, int]]:
    out = []
    for r in rows:
        lost = r.n_expected - r.n_strides
        if (r.coverage is not None and r.coverage < p.min_coverage and r.n_expected >= p.min_session_strides
                and lost >= p.min_lost_strides):
            out.append((r, lost))
    return out


def _rate_troubles(p: AttentionParams, leg: str, rows: Sequence[SessionLegEvidence]) -> list[tuple[float, str]]:
    """(effect, sentence) for every rate of one leg beyond its limit, after enough exposure."""
    expected = sum(r.n_expected for r in rows)
    n = sum(r.n_strides for r in rows)
    if expected < p.min_strides_for_rates:
        return []
    low = sum(r.n_low_quality for r in rows)
    checks = [
        (sum(r.n_expected - r.n_strides for r in rows), expected, p.max_lost_rate,
         "of its expected strides lost"),
        (low, n, p.max_low_quality_rate, "of its strides of low quality"),
        (sum(r.n_fallback for r in rows), n, p.max_fallback_rate, "of its strides from the fallback estimator"),
        (sum(r.n_implausible for r in rows), n - low, p.max_implausible_rate,
         "of its quality-passing strides with an impossible knee angle"),
    ]
    out = []
    for k, of, limit, what in checks:
        if of > 0 and k / of > limit:
            out.append((k / of / limit, f"{leg} leg: {100 * k / of:.0f} % {what} ({k} of {of}; limit "
                                        f"{100 * limit:.0f} %)"))
    return out


def sensor_flag(p: AttentionParams, rows: Sequence[SessionLegEvidence], n_failed: int) -> dict[str, Any] | None:
    """``sensor_trouble`` from the session-leg evidence of the sensor window."""
    troubles: list[tuple[float, str]] = []
    for leg in sorted({r.leg for r in rows}):
        troubles += _rate_troubles(p, leg, [r for r in rows if r.leg == leg])
    stopped = _stopped_sensors(p, rows)
    for r, lost in stopped:
        troubles.append((lost / r.n_expected / (1.0 - p.min_coverage),
                         f"{r.leg} leg sensors delivered data for only {100 * (r.coverage or 0):.0f} % of the "
                         f"session of {as_utc(r.started_at).date().isoformat()} ({lost} of {r.n_expected} strides "
                         f"lost)"))
    if n_failed > p.max_failed_sessions:
        troubles.append((n_failed / max(p.max_failed_sessions, 1), f"{n_failed} sessions failed processing"))
    if not troubles:
        return None
    n_str = sum(r.n_strides for r in rows)
    expected = sum(r.n_expected for r in rows)
    n_fb = sum(r.n_fallback for r in rows)
    n_gaps = sum(r.n_gaps for r in rows)
    walk_s = sum(r.walking_s for r in rows)
    troubles.sort(key=lambda t: -t[0])
    return {"kind": "sensor_trouble", "fallback_rate": finite_round(n_fb / n_str if n_str else None, 3),
            "lost_rate": finite_round((expected - n_str) / expected if expected else None, 3),
            "low_quality_rate": finite_round(sum(r.n_low_quality for r in rows) / n_str if n_str else None, 3),
            "gaps_per_walking_hour": finite_round(n_gaps / (walk_s / 3600.0) if walk_s >= 60.0 else None, 3),
            "n_strides": n_str, "n_expected": expected, "n_fallback": n_fb, "n_gaps": n_gaps,
            "walking_min": finite_round(walk_s / 60.0, 1), "failed_sessions": n_failed,
            "stopped_sensors": [{"leg": r.leg, "started_at": as_utc(r.started_at).isoformat(),
                                 "coverage": finite_round(r.coverage, 3), "strides_lost": lost} for r, lost in stopped],
            "effect": finite_round(troubles[0][0], 3), "reason": "; ".join(t for _, t in troubles)}


def window_json(w: stats.Window, now: datetime) -> dict[str, Any]:
    """A comparison window as JSON (times from its day offsets relative to now)."""
    return {"start": (now + timedelta(days=w.start_days)).isoformat(),
            "end": (now + timedelta(days=w.end_days)).isoformat(), "n_sessions": w.n_sessions, "n_strides": w.n,
            "mean": finite_round(w.mean, 3),
            "ci95": None if w.ci95 is None else [finite_round(w.ci95[0], 3), finite_round(w.ci95[1], 3)]}
