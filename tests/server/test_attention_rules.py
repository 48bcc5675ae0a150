"""The attention flags as pure functions: each rule against evidence whose answer is known by hand."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from server.trends import stats
from server.trends.attention import PRESETS, AttentionParams, params_for
from server.trends.attention.rules import SessionLegEvidence, change_flag, sensor_flag, silent_flag, stalled_flag
from server.trends.metrics import METRICS

NOW = datetime(2026, 11, 20, 12, 0, tzinfo=UTC)
PEAK = METRICS["peak_swing_flexion_deg"]
P = AttentionParams()


def _points(values: list[float], days: list[float] | None = None) -> list[stats.Point]:
    days = days or [-27.0 + i * 26.0 / (len(values) - 1) for i in range(len(values))]
    return [stats.Point(t, 30, v, 3.0) for t, v in zip(days, values, strict=True)]


def _ev(leg: str = "left", n: int = 36, expected: int = 36, **kw: float) -> SessionLegEvidence:
    fields = {"n_low_quality": 0, "n_fallback": 0, "n_implausible": 0, "n_gaps": 0, "walking_s": 40.0,
              "coverage": 1.0, **kw}
    return SessionLegEvidence(NOW - timedelta(days=1), leg, n, expected, **fields)  # type: ignore[arg-type]


def test_a_clear_decline_is_flagged_with_its_numbers_and_noise_is_not() -> None:
    decline = _points([64, 62.5, 61, 58, 57, 55, 52, 50])
    flag = change_flag("declining", P, PEAK, "left", decline)
    assert flag is not None and flag["kind"] == "declining"
    assert flag["slope_per_week"] == pytest.approx(-3.7, abs=0.2)
    assert flag["fitted_change"] < -5.0 and flag["p_value"] < P.alpha
    assert flag["ci95_per_week"][1] < 0
    assert "fell by" in flag["reason"] and "p = " in flag["reason"]
    assert change_flag("improving", P, PEAK, "left", decline) is None
    # A significant but clinically trivial drift (3 deg over 26 days, below the 5 deg MDC) is not a decline.
    assert change_flag("declining", P, PEAK, "left", _points([64, 63.6, 63.1, 62.7, 62.2, 61.8, 61.4, 61])) is None
    # Noise without a trend is not a decline either.
    assert change_flag("declining", P, PEAK, "left", _points([64, 60, 66, 61, 65, 62, 64, 63])) is None
    # Too few sessions say nothing.
    assert change_flag("declining", P, PEAK, "left", _points([64, 55, 50])) is None


def test_the_level_free_companion_carries_the_test_and_the_metric_the_size() -> None:
    # Peak swing flexion with session offsets of +-5 deg; ROM of the same strides without them.
    offsets = [5, -5, -5, 5, 5, -5, -5, 5]
    rom = [60 - 1.8 * i for i in range(8)]
    peak = [r + 3 + o for r, o in zip(rom, offsets, strict=True)]
    alone = change_flag("declining", P, PEAK, "left", _points(peak))
    tested = change_flag("declining", P, PEAK, "left", _points(peak), _points(rom), "rom_deg")
    assert alone is None
    assert tested is not None and tested["tested_on"] == "rom_deg"
    assert tested["fitted_change"] == pytest.approx(-12.6, abs=3.0)


def test_improving_is_low_severity_good_news_and_never_stalled() -> None:
    rise = _points([48, 50, 52.5, 55, 57, 59, 62, 64])
    flag = change_flag("improving", P, PEAK, "left", rise)
    assert flag is not None and "rose by" in flag["reason"]
    assert stalled_flag(P, PEAK, "left", rise) is None


def test_stalled_needs_a_plateau_below_the_goal_over_enough_weeks() -> None:
    flat = _points([52.2, 51.8, 52.1, 51.9, 52.0, 52.1, 51.9, 52.0])
    flag = stalled_flag(P, PEAK, "left", flat)
    assert flag is not None and flag["goal"] == 57.0 and flag["level"] == pytest.approx(52.0, abs=0.2)
    # At the goal it is a patient who has arrived.
    assert stalled_flag(P, PEAK, "left", _points([v + 12 for v in [52.2, 51.8, 52.1, 51.9, 52.0, 52.1, 51.9, 52]])) \
        is None
    # Two weeks of data cannot show a plateau.
    assert stalled_flag(P, PEAK, "left", _points([52.2, 51.8, 52.1, 51.9], [-14, -10, -5, -1])) is None
    # A noisy series whose slope CI is wide shows nothing.
    assert stalled_flag(P, PEAK, "left", _points([48, 56, 47, 57, 49, 55, 46, 56])) is None


def test_silent_follows_the_prescribed_schedule() -> None:
    last = NOW - timedelta(days=4)
    created = NOW - timedelta(days=60)
    assert silent_flag(P, NOW, last, created, None) is not None  # default 3 days
    assert silent_flag(P, NOW, last, created, 2.0) is None  # twice a week: silent after 7 days
    flag = silent_flag(P, NOW, NOW - timedelta(days=8), created, 2.0)
    assert flag is not None and flag["limit_days"] == 7.0 and "2 sessions/week" in flag["reason"]
    assert silent_flag(P, NOW, None, created, None)["last_session_at"] is None


def test_lost_packets_that_cost_no_strides_are_never_sensor_trouble() -> None:
    rows = [_ev(leg, n_gaps=40, walking_s=40.0) for leg in ("left", "right") for _ in range(4)]
    assert sensor_flag(P, rows, 0) is None


def test_strides_lost_or_degraded_after_enough_exposure_are_sensor_trouble() -> None:
    lost = [_ev("left", n=15, expected=36) for _ in range(4)] + [_ev("right") for _ in range(4)]
    flag = sensor_flag(P, lost, 0)
    assert flag is not None and "left leg: 58 % of its expected strides lost" in flag["reason"]
    assert flag["n_expected"] == 8 * 36
    # The same share in too few strides is not judged.
    assert sensor_flag(P, [_ev("left", n=5, expected=12), _ev("right", n=12, expected=12)], 0) is None
    low = [_ev("left", n_low_quality=15) for _ in range(4)]
    assert "low quality" in sensor_flag(P, low, 0)["reason"]
    fallback = [_ev("left", n_fallback=20) for _ in range(4)]
    assert "fallback" in sensor_flag(P, fallback, 0)["reason"]
    implausible = [_ev("left", n_implausible=8) for _ in range(4)]
    assert "impossible knee angle" in sensor_flag(P, implausible, 0)["reason"]
    assert "failed processing" in sensor_flag(P, [], 2)["reason"]


def test_a_sensor_that_stops_mid_session_is_trouble_when_it_cost_strides() -> None:
    stopped = [_ev("left", n=18, expected=36, coverage=0.5), _ev("right")]
    flag = sensor_flag(P, stopped, 0)
    assert flag is not None and flag["stopped_sensors"][0]["strides_lost"] == 18
    assert "50 % of the session" in flag["reason"]
    # Stopping during the standing at the end of a session costs nothing.
    assert sensor_flag(P, [_ev("left", coverage=0.7), _ev("right")], 0) is None


def test_presets_are_named_and_overridable() -> None:
    assert set(PRESETS) == {"default", "sensitive", "conservative"}
    p = params_for("sensitive", silent_days=9.0, window_days=None)
    assert p.preset == "sensitive" and p.silent_days == 9.0 and p.window_days == 14.0
    assert PRESETS["conservative"].alpha < P.alpha < PRESETS["sensitive"].alpha
    with pytest.raises(KeyError):
        params_for("unknown")
