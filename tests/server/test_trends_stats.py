"""Pure statistics of the trends view, against numbers computed by hand (see the comments)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as sps

from server.trends import stats
from server.trends.metrics import METRICS


def test_describe_small_sample_by_hand() -> None:
    d = stats.describe(np.array([1.0, 2.0, 3.0, 4.0]))
    assert d.n == 4
    assert d.mean == pytest.approx(2.5)
    assert d.sd == pytest.approx(math.sqrt(5.0 / 3.0))  # squares 2.25+0.25+0.25+2.25 = 5, / (n-1)
    assert d.median == pytest.approx(2.5)
    # Linear interpolation: position 0.1*(n-1) = 0.3 -> 1.3; 0.9*3 = 2.7 -> 3.7.
    assert d.p10 == pytest.approx(1.3)
    assert d.p90 == pytest.approx(3.7)
    assert d.cv == pytest.approx(math.sqrt(5.0 / 3.0) / 2.5)


def test_describe_edge_cases() -> None:
    assert stats.describe(np.array([])).mean is None
    one = stats.describe(np.array([7.0]))
    assert (one.n, one.mean, one.sd, one.median, one.cv) == (1, 7.0, None, 7.0, None)


def test_ols_slope_and_t_ci_by_hand() -> None:
    t = np.array([0.0, 7.0, 14.0])
    y = np.array([40.0, 46.0, 50.0])
    s = stats.ols_slope(t, y)
    # Sxx = 98, Sxy = 70 -> b = 5/7 per day; residuals -1/3, 2/3, -1/3 -> SSE = 2/3, se = sqrt(2/3 / 98).
    assert s.slope_per_day == pytest.approx(5.0 / 7.0)
    se = math.sqrt((2.0 / 3.0) / 98.0)
    half = 12.7062047 * se  # t(0.975, df=1)
    lo, hi = s.ci95_per_day
    assert lo == pytest.approx(5.0 / 7.0 - half, rel=1e-6)
    assert hi == pytest.approx(5.0 / 7.0 + half, rel=1e-6)
    per_week, ci = s.per_week()
    assert per_week == pytest.approx(5.0)
    assert ci[0] == pytest.approx(7 * lo) and ci[1] == pytest.approx(7 * hi)
    # Cross-check with scipy's regression (same estimator, independent implementation).
    ref = sps.linregress(t, y)
    assert s.slope_per_day == pytest.approx(ref.slope)
    assert (hi - s.slope_per_day) / 12.7062047 == pytest.approx(ref.stderr, rel=1e-6)
    assert s.p_value == pytest.approx(ref.pvalue, rel=1e-6)


def test_ols_degenerate_inputs() -> None:
    assert stats.ols_slope(np.array([1.0]), np.array([2.0])).slope_per_day is None
    assert stats.ols_slope(np.array([1.0, 1.0]), np.array([2.0, 3.0])).slope_per_day is None
    two = stats.ols_slope(np.array([0.0, 2.0]), np.array([1.0, 5.0]))
    assert two.slope_per_day == pytest.approx(2.0) and two.ci95_per_day is None


def test_theil_sen_resists_an_outlier() -> None:
    t = np.array([0.0, 1.0, 2.0, 3.0])
    y = np.array([0.0, 1.0, 2.0, 30.0])
    # Pairwise slopes 1, 1, 10, 1, 14.5, 28 -> median (1 + 10) / 2 = 5.5; OLS is pulled to Sxy/Sxx = 45.5/5 = 9.1.
    robust = stats.slope(t, y, "theil_sen")
    assert robust.slope_per_day == pytest.approx(5.5)
    assert robust.ci95_per_day[0] <= 5.5 <= robust.ci95_per_day[1]
    assert stats.slope(t, y, "ols").slope_per_day == pytest.approx(9.1)


def test_pool_equals_statistics_of_the_raw_values() -> None:
    rng = np.random.default_rng(3)
    groups = [rng.normal(40 + i, 3, size=n) for i, n in enumerate([5, 17, 1, 40])]
    pts = [stats.Point(float(i), g.size, float(g.mean()), float(g.std(ddof=1)) if g.size > 1 else None)
           for i, g in enumerate(groups)]
    n, mean, sd = stats.pool(pts)
    allv = np.concatenate(groups)
    assert n == allv.size
    assert mean == pytest.approx(allv.mean())
    assert sd == pytest.approx(allv.std(ddof=1))
    w = stats.window_summary(pts, 0.0, 4.0)
    assert w.mean == pytest.approx(allv.mean()) and w.sd == pytest.approx(allv.std(ddof=1))


def _pts(days: list[float], means: list[float], n: int = 30, sd: float = 2.0) -> list[stats.Point]:
    return [stats.Point(d, n, m, sd) for d, m in zip(days, means, strict=True)]


def test_change_significant_rise_between_session_windows() -> None:
    pts = _pts([0, 1, 2, 26, 27, 28], [40, 41, 42, 50, 51, 52])
    ch = stats.change(pts, mdc=5.0)
    assert ch.baseline.n_sessions == 3 and ch.latest.n_sessions == 3
    assert ch.baseline.mean == pytest.approx(41.0) and ch.latest.mean == pytest.approx(51.0)
    assert ch.delta == pytest.approx(10.0)
    # Session means sd 1 -> half width t(0.975, 2) / sqrt(3) = 4.3027 / 1.7321 = 2.484.
    assert ch.baseline.ci95[1] == pytest.approx(41.0 + 4.30265273 / math.sqrt(3.0), rel=1e-6)
    assert ch.baseline.ci_basis == "sessions"
    assert ch.significant and ch.reasons == []


def test_change_below_mdc_is_not_significant() -> None:
    ch = stats.change(_pts([0, 1, 2, 26, 27, 28], [40, 41, 42, 44, 45, 46]), mdc=5.0)
    assert ch.delta == pytest.approx(4.0)
    assert not ch.significant
    assert any("MDC" in r for r in ch.reasons)


def test_change_with_overlapping_cis_is_not_significant() -> None:
    # delta 6 > MDC, but the baseline sessions scatter so much (30, 41, 52) that the CIs overlap.
    ch = stats.change(_pts([0, 1, 2, 26, 27, 28], [30, 41, 52, 46, 47, 48]), mdc=5.0)
    assert ch.delta == pytest.approx(6.0)
    assert not ch.significant
    assert any("overlap" in r for r in ch.reasons)


def test_change_short_span_splits_the_data_in_halves() -> None:
    # Three sessions a week apart: windows shrink to 7 days, the middle session belongs to neither.
    ch = stats.change(_pts([0, 7, 14], [40, 45, 50]), mdc=5.0)
    assert ch.baseline.n_sessions == 1 and ch.latest.n_sessions == 1
    assert ch.delta == pytest.approx(10.0)
    # Fewer than 3 sessions: CI over the 30 strides, 2.045 * 2 / sqrt(30) = 0.747.
    assert ch.baseline.ci_basis == "observations"
    assert ch.baseline.ci95[1] - 40.0 == pytest.approx(float(sps.t.ppf(0.975, 29)) * 2.0 / math.sqrt(30.0))
    assert ch.significant


def test_change_needs_enough_strides_and_two_sessions() -> None:
    assert not stats.change(_pts([0.0], [40.0]), mdc=5.0).significant
    few = stats.change(_pts([0, 7, 14], [40, 45, 50], n=10), mdc=5.0, min_n=20)
    assert not few.significant and any("fewer than 20" in r for r in few.reasons)


def test_relative_mdc_scales_with_the_baseline() -> None:
    pts = [stats.Point(float(d), 1, v) for d, v in enumerate([1000, 1010, 990, 1200, 1300, 1400, 1410, 1390])]
    # Windows of 3 days: baseline days 0-2, latest days 5-7 (days 3 and 4 are in neither).
    ch = stats.change(pts, mdc=0.3, mdc_relative=True, window_days=3.0, min_n=3)
    assert ch.mdc == pytest.approx(300.0)  # 30 % of the baseline mean 1000
    assert ch.delta == pytest.approx(400.0)
    assert ch.significant


def test_metric_plausibility_limits() -> None:
    peak = METRICS["peak_swing_flexion_deg"]
    ok = peak.plausible(np.array([-1.0, 0.0, 65.0, 140.0, 141.0, np.nan]))
    assert ok.tolist() == [False, True, True, True, False, False]
    cadence = METRICS["cadence_steps_per_min"]
    assert cadence.values(np.array([1.2]))[0] == pytest.approx(100.0)  # 2 steps per 1.2 s stride


def test_describe_segments_matches_describe_per_segment() -> None:
    rng = np.random.default_rng(5)
    lengths = np.array([5, 0, 1, 2, 300, 17])
    values = rng.normal(50, 10, lengths.sum())
    out = stats.describe_segments(values, lengths)
    start = 0
    for seg, n in zip(out, lengths, strict=True):
        ref = stats.describe(values[start:start + n])
        start += n
        assert seg.n == ref.n
        for field in ("mean", "sd", "median", "p10", "p90", "cv"):
            a, b = getattr(seg, field), getattr(ref, field)
            assert (a is None and b is None) or a == pytest.approx(b, rel=1e-12), field
    # And both agree with numpy's own percentile.
    big = values[lengths[:4].sum():lengths[:5].sum()]
    assert out[4].p10 == pytest.approx(np.percentile(big, 10))
    assert out[4].median == pytest.approx(np.median(big))


def test_describe_segments_trusts_presorted_segments() -> None:
    values = np.array([1.0, 2.0, 3.0, 9.0, 7.0, 8.0])
    out = stats.describe_segments(values, np.array([3, 3]), presorted=np.array([True, False]))
    assert (out[0].median, out[1].median) == (2.0, 8.0)
    assert out[1].p10 == pytest.approx(7.2)  # sorted 7, 8, 9: 7 + 0.2 * 1
