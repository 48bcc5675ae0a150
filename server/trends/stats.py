"""Pure statistics of the trends view: bucket descriptives, slope with a 95 % CI, baseline-vs-latest change.

No database, no web: numpy/scipy in, dataclasses out, so every number can be checked by hand in tests.

Conventions
- ``sd`` is the sample standard deviation (ddof=1); ``None`` with fewer than two values.
- Percentiles use numpy's default linear interpolation (Hyndman-Fan type 7, as R and Excel PERCENTILE.INC).
- ``cv`` is sd / mean as a fraction (``None`` when the mean is 0 or sd undefined).
- A "session point" summarises one session (or, for count metrics, one day) by its number of observations, mean and
  sd; windows pool session points exactly (pooled mean and variance from per-session n, mean, sd).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal

import numpy as np
from scipy import stats as sps

SlopeMethod = Literal["ols", "theil_sen"]


@dataclass(frozen=True)
class Describe:
    """Descriptive statistics of a set of values."""

    n: int
    mean: float | None
    sd: float | None
    median: float | None
    p10: float | None
    p90: float | None
    cv: float | None


def quantiles_sorted(v: np.ndarray, qs: Sequence[float]) -> list[float]:
    """Type-7 quantiles of an ascending array: h = (n - 1) q, v[floor h] + (h - floor h) (v[floor h + 1] - ...).

    The same numbers as ``np.percentile`` (default method) at a fraction of its per-call overhead, which matters for
    a year of daily buckets."""
    n = v.size
    out = []
    for q in qs:
        h = (n - 1) * q
        lo = int(math.floor(h))
        hi = min(lo + 1, n - 1)
        out.append(float(v[lo] + (h - lo) * (v[hi] - v[lo])))
    return out


def describe(values: np.ndarray) -> Describe:
    """Descriptive statistics of the included values of one bucket (NaN must already be removed)."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    n = int(v.size)
    if n == 0:
        return Describe(0, None, None, None, None, None, None)
    mean = float(v.mean())
    sd = float(math.sqrt(float(np.dot(v - mean, v - mean)) / (n - 1))) if n >= 2 else None
    p10, median, p90 = quantiles_sorted(v, (0.1, 0.5, 0.9))
    cv = sd / mean if sd is not None and mean != 0 else None
    return Describe(n, mean, sd, median, p10, p90, cv)


def describe_segments(values: np.ndarray, lengths: np.ndarray, presorted: np.ndarray | None = None) -> list[Describe]:
    """:func:`describe` of consecutive segments of ``values`` (segment i has ``lengths[i]`` values), vectorised:
    a few reductions for a whole year of buckets instead of a Python loop of numpy calls. ``presorted[i]`` True
    says segment i is already ascending (it is then not sorted again)."""
    lengths = np.asarray(lengths, dtype=np.int64)
    k = lengths.size
    if k == 0:
        return []
    v = np.asarray(values, dtype=np.float64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    if presorted is None:
        seg = np.repeat(np.arange(k), lengths)
        vs = v[np.lexsort((v, seg))]  # sorted within each segment, segments in order
    else:
        vs = v.copy()
        for i in np.flatnonzero(~np.asarray(presorted, dtype=bool) & (lengths > 1)):
            vs[starts[i]:starts[i] + lengths[i]].sort()
    nonempty = lengths > 0
    safe_starts = np.minimum(starts, max(v.size - 1, 0))
    sums = np.add.reduceat(vs, safe_starts) if v.size else np.zeros(k)
    sums = np.where(nonempty, sums, 0.0)
    n = np.maximum(lengths, 1)
    means = sums / n
    dev = vs - np.repeat(means, lengths)
    ss = np.add.reduceat(dev * dev, safe_starts) if v.size else np.zeros(k)
    ss = np.where(nonempty, ss, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sds = np.sqrt(ss / (lengths - 1))

    def q(frac: float) -> np.ndarray:
        h = (lengths - 1) * frac
        lo = np.floor(h).astype(np.int64)
        hi = np.minimum(lo + 1, lengths - 1)
        lo_v = vs[np.clip(starts + lo, 0, max(v.size - 1, 0))] if v.size else np.zeros(k)
        hi_v = vs[np.clip(starts + hi, 0, max(v.size - 1, 0))] if v.size else np.zeros(k)
        return lo_v + (h - lo) * (hi_v - lo_v)

    p10, med, p90 = q(0.1), q(0.5), q(0.9)
    out = []
    for i in range(k):
        m = int(lengths[i])
        if m == 0:
            out.append(Describe(0, None, None, None, None, None, None))
            continue
        mean = float(means[i])
        sd = float(sds[i]) if m >= 2 else None
        out.append(Describe(m, mean, sd, float(med[i]), float(p10[i]), float(p90[i]),
                            sd / mean if sd is not None and mean != 0 else None))
    return out


@lru_cache(maxsize=4096)
def t_quantile(df: int, q: float = 0.975) -> float:
    """t(q, df), cached: scipy's ppf costs ~0.3 ms a call and the attention list needs thousands."""
    return float(sps.t.ppf(q, df))


@dataclass(frozen=True)
class Slope:
    """Slope of the values over time in units per day, with its 95 % confidence interval."""

    method: SlopeMethod
    n: int
    slope_per_day: float | None
    intercept: float | None
    ci95_per_day: tuple[float, float] | None
    p_value: float | None = None

    def per_week(self) -> tuple[float | None, tuple[float, float] | None]:
        slope = None if self.slope_per_day is None else 7.0 * self.slope_per_day
        ci = None if self.ci95_per_day is None else (7.0 * self.ci95_per_day[0], 7.0 * self.ci95_per_day[1])
        return slope, ci


def ols_slope(t_days: np.ndarray, y: np.ndarray) -> Slope:
    """Ordinary least squares y = a + b t with a t-based 95 % CI for b.

    b = Sxy / Sxx, s^2 = SSE / (n - 2), se(b) = sqrt(s^2 / Sxx), CI = b -/+ t(0.975, n - 2) se(b)
    (any regression textbook, e.g. Montgomery & Runger, Applied Statistics, eq. 11-21). Two points give a slope but no
    CI (zero residual degrees of freedom); one point or identical times give neither.
    """
    t = [float(x) for x in np.asarray(t_days, dtype=np.float64)]
    n = len(t)
    fit = ols_fit(t, [float(x) for x in np.asarray(y, dtype=np.float64)])
    if fit is None:
        return Slope("ols", n, None, None, None)
    b, a, se = fit
    if se is None:
        return Slope("ols", n, b, a, None)
    tq = t_quantile(n - 2)
    p = float(2.0 * sps.t.sf(abs(b) / se, n - 2)) if se > 0 else 0.0
    return Slope("ols", n, b, a, (b - tq * se, b + tq * se), p)


def ols_fit(t: Sequence[float], y: Sequence[float]) -> tuple[float, float, float | None] | None:
    """Least squares y = a + b t in plain Python (a few points cost microseconds, numpy's call overhead would
    dominate): (b, a, se(b)) with se None for two points; None for fewer points or identical times."""
    n = len(t)
    if n < 2:
        return None
    tm = sum(t) / n
    ym = sum(y) / n
    sxx = sum((x - tm) ** 2 for x in t)
    if sxx <= 0.0:
        return None
    b = sum((x - tm) * (v - ym) for x, v in zip(t, y, strict=True)) / sxx
    a = ym - b * tm
    if n < 3:
        return b, a, None
    sse = sum((v - (a + b * x)) ** 2 for x, v in zip(t, y, strict=True))
    return b, a, math.sqrt(sse / (n - 2) / sxx)


def theil_sen_slope(t_days: np.ndarray, y: np.ndarray) -> Slope:
    """Theil-Sen estimator (median of pairwise slopes) with Sen's (1968) 95 % CI, via scipy.stats.theilslopes.

    Robust to outlying sessions (breakdown point ~29 %); the CI is distribution-free (based on Kendall's tau).
    """
    t = np.asarray(t_days, dtype=np.float64)
    v = np.asarray(y, dtype=np.float64)
    n = int(t.size)
    if n < 2 or float(np.ptp(t)) <= 0.0:
        return Slope("theil_sen", n, None, None, None)
    res = sps.theilslopes(v, t, alpha=0.95)
    ci = (float(res.low_slope), float(res.high_slope)) if n >= 3 else None
    if ci is not None and not all(math.isfinite(c) for c in ci):
        ci = None
    return Slope("theil_sen", n, float(res.slope), float(res.intercept), ci)


def slope(t_days: np.ndarray, y: np.ndarray, method: SlopeMethod = "ols") -> Slope:
    """Slope of ``y`` over ``t`` (days) by least squares or Theil-Sen, with its 95 % CI."""
    return theil_sen_slope(t_days, y) if method == "theil_sen" else ols_slope(t_days, y)


@dataclass(frozen=True)
class Point:
    """One session (or one day for count metrics): time in days, number of observations, their mean and sd."""

    t_days: float
    n: int
    mean: float
    sd: float | None = None


def pool(points: Sequence[Point]) -> tuple[int, float | None, float | None]:
    """Exact pooled (n, mean, sd) of the observations behind the points.

    Pooled variance = (sum (n_i - 1) s_i^2 + sum n_i (m_i - M)^2) / (N - 1) (the within + between decomposition);
    a point without sd (one observation) contributes no within-point variance.
    """
    n_tot = sum(p.n for p in points)
    if n_tot == 0:
        return 0, None, None
    mean = sum(p.n * p.mean for p in points) / n_tot
    if n_tot < 2:
        return n_tot, mean, None
    ss = sum((p.n - 1) * (p.sd or 0.0) ** 2 + p.n * (p.mean - mean) ** 2 for p in points)
    return n_tot, mean, math.sqrt(max(ss, 0.0) / (n_tot - 1))


@dataclass(frozen=True)
class Window:
    """The session-level statistics of one time window."""

    start_days: float
    end_days: float
    n_sessions: int
    n: int  # observations (strides; days for count metrics)
    mean: float | None
    sd: float | None
    ci95: tuple[float, float] | None
    ci_basis: str  # "sessions" (between-session) or "observations" (within-session, fewer than 3 sessions)


def _t_ci(mean: float, sd: float, n: int) -> tuple[float, float]:
    half = t_quantile(n - 1) * sd / math.sqrt(n)
    return mean - half, mean + half


def window_from_moments(start_days: float, end_days: float, *, k: int, n: int, s1: float, s2: float, m1: float,
                        m2: float) -> Window:
    """A window from aggregated moments (so SQL can do the summing): ``k`` sessions, ``n`` observations,
    s1 = sum n_i m_i, s2 = sum ((n_i - 1) s_i^2 + n_i m_i^2) (the observations' sum of squares),
    m1 = sum m_i, m2 = sum m_i^2 over the session means. Same CI rule as :func:`window_summary`."""
    if n <= 0 or k <= 0:
        return Window(start_days, end_days, k, n, None, None, None, "observations")
    mean = s1 / n
    sd = math.sqrt(max(s2 - n * mean * mean, 0.0) / (n - 1)) if n >= 2 else None
    if k >= 3:
        sm = m1 / k
        ssd = math.sqrt(max(m2 - k * sm * sm, 0.0) / (k - 1))
        return Window(start_days, end_days, k, n, mean, sd, _t_ci(sm, ssd, k), "sessions")
    ci = _t_ci(mean, sd, n) if sd is not None else None
    return Window(start_days, end_days, k, n, mean, sd, ci, "observations")


def window_summary(points: Sequence[Point], start_days: float, end_days: float) -> Window:
    """Mean of a window with a 95 % CI.

    With >= 3 sessions the CI is t-based over the session means (between-session variability is what a repeated
    measurement would see); with fewer it falls back to the pooled observations (mean -/+ t * sd / sqrt(n)), which is
    narrower and says so in ``ci_basis``.
    """
    return window_from_moments(
        start_days, end_days, k=len(points), n=sum(p.n for p in points),
        s1=sum(p.n * p.mean for p in points),
        s2=sum((p.n - 1) * (p.sd or 0.0) ** 2 + p.n * p.mean ** 2 for p in points),
        m1=sum(p.mean for p in points), m2=sum(p.mean ** 2 for p in points),
    )


@dataclass(frozen=True)
class Change:
    """Baseline vs latest window: the difference and whether it is significant."""

    baseline: Window | None
    latest: Window | None
    delta: float | None
    mdc: float | None
    significant: bool
    reasons: list[str] = field(default_factory=list)


def change(points: Sequence[Point], *, mdc: float, mdc_relative: bool = False, window_days: float = 14.0,
           min_n: int = 20) -> Change:
    """Baseline window (the first ``window_days`` from the first point) vs latest window (the last ``window_days``
    up to the last point).

    When the data span less than two windows the windows shrink to half the span each, so they never overlap
    (points exactly at the midpoint then belong to neither). ``significant`` needs all of: |delta| > MDC, both
    windows with >= ``min_n`` observations, and non-overlapping 95 % CIs. ``mdc_relative``: the MDC is that
    fraction of the baseline mean.
    """
    pts = sorted(points, key=lambda p: p.t_days)
    if len(pts) < 2:
        return Change(None, None, None, None if mdc_relative else mdc, False, ["needs data from two sessions"])
    first, last = pts[0].t_days, pts[-1].t_days
    span = last - first
    if span <= 0:
        return Change(None, None, None, None if mdc_relative else mdc, False, ["all data at one time"])
    w = min(window_days, span / 2.0)
    base = [p for p in pts if p.t_days < first + w]
    late = [p for p in pts if p.t_days > last - w]
    return compare(window_summary(base, first, first + w), window_summary(late, last - w, last), mdc=mdc,
                   mdc_relative=mdc_relative, min_n=min_n)


def compare(bw: Window, lw: Window, *, mdc: float, mdc_relative: bool = False, min_n: int = 20) -> Change:
    """Latest minus baseline with the significance rule of :func:`change`."""
    reasons: list[str] = []
    if bw.mean is None or lw.mean is None:
        return Change(bw, lw, None, None if mdc_relative else mdc, False, ["a window has no data"])
    delta = lw.mean - bw.mean
    eff_mdc = mdc * abs(bw.mean) if mdc_relative else mdc
    significant = True
    if abs(delta) <= eff_mdc:
        significant = False
        reasons.append(f"|delta| {abs(delta):.3g} <= MDC {eff_mdc:.3g}")
    if bw.n < min_n or lw.n < min_n:
        significant = False
        reasons.append(f"fewer than {min_n} observations in a window (baseline {bw.n}, latest {lw.n})")
    if bw.ci95 is None or lw.ci95 is None:
        significant = False
        reasons.append("a window has no confidence interval")
    elif not (bw.ci95[1] < lw.ci95[0] or lw.ci95[1] < bw.ci95[0]):
        significant = False
        reasons.append("the windows' 95 % CIs overlap")
    return Change(bw, lw, delta, eff_mdc, significant, reasons)
