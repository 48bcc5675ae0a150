"""Trend summaries and views on SQLite and PostgreSQL with known strides (hand-computable expectations)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

from server.auth.models import Clinician
from server.codec import decode_values
from server.db import make_engine, make_sessionmaker
from server.patients.models import Patient
from server.sessions.models import Session
from server.trends import service
from server.trends.attention import AttentionParams, attention_list
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.summaries import backfill, refresh_session, stale_session_ids
from server.trends.timeutil import parse_bound, zone
from tests.support.seed import add_session

NOW = datetime(2026, 11, 20, 12, 0, tzinfo=UTC)


@pytest.fixture
def factory(database_url: str) -> Iterator:
    engine = make_engine(database_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def _patient(db: DbSession, *, tz: str = "UTC", affected: str | None = "left", clinician: str | None = None,
             created: datetime | None = None) -> Patient:
    if clinician is None:
        c = Clinician(name="Dr. T")
        db.add(c)
        db.flush()
        clinician = c.id
    p = Patient(clinician_id=clinician, timezone=tz, affected_leg=affected, display_name="P",
                created_at=created or NOW - timedelta(days=90))
    db.add(p)
    db.flush()
    return p


def _alternating(a: float, b: float, n: int) -> np.ndarray:
    return np.where(np.arange(n) % 2 == 0, a, b)


def test_refresh_counts_quality_and_plausibility_exclusions(factory) -> None:
    with factory() as db:
        p = _patient(db)
        peaks = np.array([50, 51, 52, 53, 54, 55, 56, 150, 58, 59], dtype=float)
        quality = np.array([1, 1, 0.2, 1, 1, 0.1, 1, 1, 1, 1], dtype=float)
        sid = add_session(db, p.id, NOW, {"left": {"n": 10, "peak_swing_flexion_deg": peaks, "quality": quality,
                                                    "estimator": ["go"] * 7 + ["cf"] * 3,
                                                    "fallback": [False] * 7 + [True] * 3}})
        db.commit()
        leg = db.get(TrendSessionLeg, (sid, "left", "walking"))
        assert (leg.n_strides, leg.n_low_quality, leg.n_fallback) == (10, 2, 3)
        peak = db.get(TrendMetricValues, (sid, "left", "walking", "peak_swing_flexion_deg"))
        # quality drops 52 and 55; plausibility drops 150 (> 140 deg).
        assert (peak.n_included, peak.n_implausible) == (7, 1)
        expected = [50, 51, 53, 54, 56, 58, 59]
        assert decode_values(peak.values).tolist() == expected
        assert peak.mean == pytest.approx(np.mean(expected))
        assert peak.median == pytest.approx(54.0)
        rom = db.get(TrendMetricValues, (sid, "left", "walking", "rom_deg"))
        assert rom.n_implausible == 1  # 150 - 2 = 148 deg ROM is implausible too
        cad = db.get(TrendMetricValues, (sid, "left", "walking", "cadence_steps_per_min"))
        assert cad.mean == pytest.approx(120.0 / 1.1)


def test_refresh_of_a_failed_session_removes_its_summaries(factory) -> None:
    with factory() as db:
        p = _patient(db)
        sid = add_session(db, p.id, NOW, {"left": {"n": 10}})
        db.commit()
        db.get(Session, sid).status = "failed"
        db.flush()
        assert refresh_session(db, sid) == 0
        db.commit()
        assert db.scalars(select(TrendSessionLeg).where(TrendSessionLeg.session_id == sid)).all() == []
        assert db.scalars(select(TrendMetricValues).where(TrendMetricValues.session_id == sid)).all() == []


def _three_weekly_sessions(db: DbSession, p: Patient, t0: datetime) -> None:
    # 20 strides each alternating a/b: means 40, 45, 51; sd sqrt(20 / 19); p10 a, p90 b.
    for k, (a, b) in enumerate([(39, 41), (44, 46), (50, 52)]):
        spec = {"n": 20, "peak_swing_flexion_deg": _alternating(a, b, 20)}
        add_session(db, p.id, t0 + timedelta(days=7 * k), {"left": spec})


def test_daily_trend_buckets_slope_and_change_by_hand(factory) -> None:
    with factory() as db:
        p = _patient(db)
        t0 = datetime(2026, 10, 5, 9, 0, tzinfo=UTC)
        _three_weekly_sessions(db, p, t0)
        db.commit()
        out = service.patient_trends(db, p, metric_name="peak_swing_flexion_deg", leg=None, bucket="day",
                                     start=None, end=None)
    assert out["leg"] == "left" and out["unit"] == "deg"
    b = out["buckets"]
    assert [x["start"] for x in b] == ["2026-10-05T00:00:00+00:00", "2026-10-12T00:00:00+00:00",
                                       "2026-10-19T00:00:00+00:00"]
    assert [x["mean"] for x in b] == [40.0, 45.0, 51.0]
    assert [x["median"] for x in b] == [40.0, 45.0, 51.0]
    assert [(x["p10"], x["p90"]) for x in b] == [(39.0, 41.0), (44.0, 46.0), (50.0, 52.0)]
    assert all(x["n_strides"] == 20 and x["n_sessions"] == 1 and x["n_excluded"] == 0 for x in b)
    assert b[0]["sd"] == pytest.approx(math.sqrt(20 / 19), abs=1e-4)
    assert b[0]["cv"] == pytest.approx(math.sqrt(20 / 19) / 40, abs=1e-4)
    # Session means 40, 45, 51 at days 0, 7, 14: Sxy = 77, Sxx = 98 -> 77/98 per day = 5.5 per week.
    tr = out["trend"]
    assert tr["n"] == 3 and tr["method"] == "ols"
    assert tr["slope_per_week"] == pytest.approx(5.5)
    assert tr["ci95"][0] < 5.5 < tr["ci95"][1]
    ch = out["change"]
    # Span 14 days -> 7-day windows: baseline = session 1, latest = session 3.
    assert (ch["baseline"], ch["latest"], ch["delta"], ch["mdc"]) == (40.0, 51.0, 11.0, 5.0)
    assert ch["significant"] is True and ch["direction"] == "improved"
    assert ch["baseline_window"]["n_sessions"] == 1 and ch["latest_window"]["n"] == 20


def test_weekly_bucket_pools_strides_of_all_sessions(factory) -> None:
    with factory() as db:
        p = _patient(db)
        monday = datetime(2026, 10, 5, 9, 0, tzinfo=UTC)  # 2026-10-05 is a Monday
        add_session(db, p.id, monday, {"left": {"n": 20, "peak_swing_flexion_deg": _alternating(39, 41, 20)}})
        add_session(db, p.id, monday + timedelta(days=6, hours=10),
                    {"left": {"n": 20, "peak_swing_flexion_deg": _alternating(42, 44, 20)}})
        add_session(db, p.id, monday + timedelta(days=7), {"left": {"n": 10}})
        db.commit()
        out = service.patient_trends(db, p, metric_name="peak_swing_flexion_deg", leg="left", bucket="week",
                                     start=None, end=None, method="theil_sen")
    b = out["buckets"]
    assert [x["start"] for x in b] == ["2026-10-05T00:00:00+00:00", "2026-10-12T00:00:00+00:00"]
    assert b[0]["n_sessions"] == 2 and b[0]["n_strides"] == 40
    assert b[0]["mean"] == pytest.approx(41.5)  # (39 + 41 + 42 + 44) / 4
    assert b[0]["median"] == pytest.approx(41.5)
    assert b[1]["mean"] == pytest.approx(60.0) and b[1]["n_strides"] == 10
    assert out["trend"]["method"] == "theil_sen" and out["trend"]["n"] == 3


def test_local_midnight_and_dst_in_the_patients_zone(factory) -> None:
    with factory() as db:
        p = _patient(db, tz="Europe/Berlin")
        # 23:30 UTC on 10 March is 00:30 on 11 March in Berlin (UTC+1); 22:30 UTC is still 10 March.
        add_session(db, p.id, datetime(2026, 3, 10, 23, 30, tzinfo=UTC), {"left": {"n": 10}})
        add_session(db, p.id, datetime(2026, 3, 10, 22, 30, tzinfo=UTC),
                    {"left": {"n": 10, "peak_swing_flexion_deg": 50.0}})
        # 29 March 2026 is the EU switch to summer time: that local day has 23 hours.
        add_session(db, p.id, datetime(2026, 3, 29, 10, 0, tzinfo=UTC), {"left": {"n": 10}})
        db.commit()
        out = service.patient_trends(db, p, metric_name="peak_swing_flexion_deg", leg="left", bucket="day",
                                     start=None, end=None)
        b = out["buckets"]
        assert [(x["start"], x["mean"]) for x in b] == [
            ("2026-03-10T00:00:00+01:00", 50.0), ("2026-03-11T00:00:00+01:00", 60.0),
            ("2026-03-29T00:00:00+01:00", 60.0)]
        assert b[2]["end"] == "2026-03-30T00:00:00+02:00"
        # A local-date range selects by local day: only the session of 11 March (local).
        tz = zone(p.timezone)
        lo, hi = parse_bound("2026-03-11", tz, end=False), parse_bound("2026-03-11", tz, end=True)
        only = service.patient_trends(db, p, metric_name="peak_swing_flexion_deg", leg="left", bucket="day",
                                      start=lo, end=hi)
        assert [x["start"] for x in only["buckets"]] == ["2026-03-11T00:00:00+01:00"]


def test_strides_per_day_counts_trustworthy_strides_per_local_day(factory) -> None:
    with factory() as db:
        p = _patient(db)
        day = datetime(2026, 10, 5, 8, 0, tzinfo=UTC)
        add_session(db, p.id, day, {"left": {"n": 30}})
        add_session(db, p.id, day + timedelta(hours=6),
                    {"left": {"n": 20, "quality": np.r_[np.ones(15), np.zeros(5)]}})
        add_session(db, p.id, day + timedelta(days=1), {"left": {"n": 12}})
        db.commit()
        out = service.patient_trends(db, p, metric_name="strides_per_day", leg="left", bucket="day",
                                     start=None, end=None)
    b = out["buckets"]
    assert [x["mean"] for x in b] == [45.0, 12.0]
    assert b[0]["n_excluded"] == 5 and b[0]["n_sessions"] == 2
    assert out["trend"]["slope_per_week"] == pytest.approx(-33.0 * 7)  # two days: 45 -> 12
    assert out["excluded"]["n_low_quality"] == 5


def test_default_leg_is_the_affected_leg_or_the_leg_with_data(factory) -> None:
    with factory() as db:
        p = _patient(db, affected="right")
        add_session(db, p.id, NOW, {"left": {"n": 10}})
        db.commit()
        assert service.default_leg(db, p) == "left"  # affected leg has no data
        add_session(db, p.id, NOW + timedelta(hours=1), {"right": {"n": 5}})
        db.commit()
        assert service.default_leg(db, p) == "right"


def test_symmetry_index_of_bucket_means(factory) -> None:
    with factory() as db:
        p = _patient(db, affected="left")
        add_session(db, p.id, NOW, {"left": {"n": 10, "peak_swing_flexion_deg": 40.0},
                                    "right": {"n": 10, "peak_swing_flexion_deg": 60.0}})
        db.commit()
        out = service.patient_symmetry(db, p, metric_name="peak_swing_flexion_deg", bucket="day", start=None,
                                       end=None)
    (b,) = out["buckets"]
    assert out["reference_leg"] == "left" and out["other_leg"] == "right"
    assert b["ratio"] == pytest.approx(40 / 60, abs=1e-4)
    assert b["symmetry_index_pct"] == pytest.approx(-40.0)  # 100 * (40 - 60) / 50


def test_completeness_days_strides_and_walking_minutes(factory) -> None:
    with factory() as db:
        p = _patient(db, tz="America/New_York")
        now = datetime(2026, 11, 20, 15, 0, tzinfo=UTC)  # 10:00 in New York
        add_session(db, p.id, now - timedelta(hours=1), {"left": {"n": 100}, "right": {"n": 90}})
        add_session(db, p.id, now - timedelta(days=2), {"left": {"n": 50}})
        add_session(db, p.id, now - timedelta(days=40), {"left": {"n": 50}})  # outside 30 days
        db.commit()
        out = service.patient_completeness(db, p, days=30, now=now)
    assert out["to"] == "2026-11-20" and out["from"] == "2026-10-22"
    assert len(out["per_day"]) == 30
    assert out["days_with_data"] == 2
    days = {d["date"]: d for d in out["per_day"]}
    # Busiest leg per session: 100 strides of 1.1 s = 110 s = 1.83 min.
    assert days["2026-11-20"]["n_strides"] == 100
    assert days["2026-11-20"]["walking_min"] == pytest.approx(110 / 60, abs=0.01)
    assert days["2026-11-18"]["n_strides"] == 50
    assert out["strides_total"] == 150


def test_backfill_summarises_sessions_without_summary(factory) -> None:
    with factory() as db:
        p = _patient(db)
        sid = add_session(db, p.id, NOW, {"left": {"n": 10}}, refresh=False)
        db.commit()
        assert stale_session_ids(db) == [sid]
    assert backfill(factory) == 1
    with factory() as db:
        assert db.get(TrendSessionLeg, (sid, "left", "walking")).n_strides == 10
        assert stale_session_ids(db) == []
    assert backfill(factory) == 0


def _sessions(db: DbSession, p: Patient, days_ago: list[float], peak: float | list[float], n: int = 30,
              **extra) -> None:
    peaks = peak if isinstance(peak, list) else [peak] * len(days_ago)
    for d, v in zip(days_ago, peaks, strict=True):
        add_session(db, p.id, NOW - timedelta(days=d),
                    {"left": {"n": n, "peak_swing_flexion_deg": _alternating(v - 1, v + 1, n), **extra}})


def test_attention_flags_declining_stalled_improving_silent_and_sensor_trouble(factory) -> None:
    with factory() as db:
        c = Clinician(name="Dr. A")
        other = Clinician(name="Dr. B")
        db.add_all([c, other])
        db.flush()
        declining = _patient(db, clinician=c.id)
        _sessions(db, declining, [27, 24, 21, 12, 8, 1], [60, 61, 59, 45, 46, 44])
        stalled = _patient(db, clinician=c.id)
        _sessions(db, stalled, [27, 24, 21, 12, 8, 1], [50, 51, 49, 50, 51, 49])
        improving = _patient(db, clinician=c.id)
        _sessions(db, improving, [27, 24, 21, 12, 8, 1], [40, 41, 39, 55, 56, 54])
        silent = _patient(db, clinician=c.id)
        _sessions(db, silent, [5], 50)
        troubled = _patient(db, clinician=c.id)
        _sessions(db, troubled, [2, 1], [50, 50], n=60, estimator=["go"] * 20 + ["cf"] * 40,
                  fallback=[False] * 20 + [True] * 40)
        foreign = _patient(db, clinician=other.id)
        _sessions(db, foreign, [27, 24, 21, 12, 8, 1], [60, 61, 59, 45, 46, 44])
        db.commit()
        out = attention_list(db, clinician_id=c.id, params=AttentionParams(), now=NOW)
        admin = attention_list(db, clinician_id=None, params=AttentionParams(), now=NOW)
        first_page = attention_list(db, clinician_id=c.id, now=NOW, limit=2)
        second_page = attention_list(db, clinician_id=c.id, now=NOW, limit=2,
                                     offset=int(first_page["next_cursor"]))

    kinds = {it["patient"]["id"]: [f["kind"] for f in it["flags"]] for it in out["items"]}
    assert kinds[declining.id] == ["declining"]
    assert kinds[stalled.id] == ["stalled"]
    assert kinds[improving.id] == ["improving"]
    assert kinds[silent.id] == ["silent"]
    assert kinds[troubled.id] == ["sensor_trouble"]
    assert foreign.id not in kinds and out["n_patients"] == 5
    assert foreign.id in {it["patient"]["id"] for it in admin["items"]}
    # The most severe first, with the numbers behind the flag.
    assert out["items"][0]["patient"]["id"] == declining.id
    flag = out["items"][0]["flags"][0]
    assert flag["delta"] == pytest.approx(-15.0) and flag["mdc"] == 5.0
    assert flag["baseline"]["mean"] == pytest.approx(60.0) and flag["latest"]["mean"] == pytest.approx(45.0)
    assert flag["slope_per_week"] < 0 and flag["p_value"] < 0.01 and flag["fitted_change"] < -5.0
    assert flag["ci95_per_week"][1] < 0 and flag["n_sessions"] == 6
    # Good news comes last: improving is the least severe item.
    assert out["items"][-1]["patient"]["id"] == improving.id and out["items"][-1]["severity"] == 0
    assert set(out["rules"]) >= {"declining", "improving", "stalled", "silent", "sensor_trouble"}
    trouble = next(it for it in out["items"] if it["patient"]["id"] == troubled.id)["flags"][0]
    assert trouble["fallback_rate"] == pytest.approx(80 / 120, abs=1e-3)
    silent_flag = next(it for it in out["items"] if it["patient"]["id"] == silent.id)["flags"][0]
    assert silent_flag["days_without_data"] == pytest.approx(5.0)
    # Pagination covers every flagged patient exactly once.
    ids = [it["patient"]["id"] for it in first_page["items"] + second_page["items"]]
    assert len(first_page["items"]) == 2 and len(ids) == len(set(ids))
    assert set(ids) <= set(kinds)


def test_summaries_without_stored_quantiles_fall_back_to_the_value_arrays(factory) -> None:
    with factory() as db:
        p = _patient(db)
        peaks = np.arange(40.0, 61.0)  # 21 values: p10 = 42, median 50, p90 = 58
        add_session(db, p.id, NOW, {"left": {"n": 21, "peak_swing_flexion_deg": peaks[::-1]}})
        db.commit()
        stored = service.patient_trends(db, p, metric_name="peak_swing_flexion_deg", leg="left", bucket="day",
                                        start=None, end=None)["buckets"][0]
        # Rows written before migration 0003 have no p10/p90.
        for row in db.scalars(select(TrendMetricValues)):
            row.p10 = row.p90 = None
        db.commit()
        fallback = service.patient_trends(db, p, metric_name="peak_swing_flexion_deg", leg="left", bucket="day",
                                          start=None, end=None)["buckets"][0]
    assert (stored["p10"], stored["median"], stored["p90"]) == (42.0, 50.0, 58.0)
    assert (fallback["p10"], fallback["median"], fallback["p90"]) == (42.0, 50.0, 58.0)


def test_the_precomputed_attention_evidence_matches_the_live_computation(factory) -> None:
    """Flags read from the evidence kept at processing time equal those computed live (windows ending at the
    latest session), and a patient's evidence follows their new sessions."""
    with factory() as db:
        c = Clinician(name="Dr. E")
        db.add(c)
        db.flush()
        declining = _patient(db, clinician=c.id)
        _sessions(db, declining, [27, 24, 21, 12, 8, 1], [60, 61, 59, 45, 46, 44])
        improving = _patient(db, clinician=c.id)
        _sessions(db, improving, [27, 24, 21, 12, 8, 1], [40, 41, 39, 55, 56, 54])
        troubled = _patient(db, clinician=c.id)
        _sessions(db, troubled, [2, 1], [50, 50], n=60, fallback=[False] * 20 + [True] * 40)
        db.commit()
        last = NOW - timedelta(days=1)
        cached = attention_list(db, clinician_id=c.id, now=NOW)
        live = attention_list(db, clinician_id=c.id, now=last, live=True)

        def kinds(out: dict) -> dict[str, list[str]]:
            return {it["patient"]["id"]: [f["kind"] for f in it["flags"] if f["kind"] != "silent"]
                    for it in out["items"]}

        assert kinds(cached) == kinds(live) == {declining.id: ["declining"], improving.id: ["improving"],
                                                troubled.id: ["sensor_trouble"]}
        d_cached = next(it for it in cached["items"] if it["patient"]["id"] == declining.id)["flags"][0]
        d_live = next(it for it in live["items"] if it["patient"]["id"] == declining.id)["flags"][0]
        assert d_cached["p_value"] == d_live["p_value"] and d_cached["fitted_change"] == d_live["fitted_change"]
        # Two more sessions back at the old level: the decline is gone from the evidence.
        _sessions(db, declining, [0.5, 0.2], [60, 61])
        db.commit()
        after = attention_list(db, clinician_id=c.id, now=NOW)
    assert declining.id not in kinds(after) or "declining" not in kinds(after)[declining.id]


def test_latest_session_means_and_per_session_medians_count_only_trustworthy_strides(factory) -> None:
    with factory() as db:
        p = _patient(db)
        other = _patient(db)
        old = add_session(db, p.id, NOW - timedelta(days=2),
                          {"left": {"n": 4, "peak_swing_flexion_deg": [40, 42, 44, 150]},
                           "right": {"n": 3, "peak_swing_flexion_deg": 61.0}})
        new = add_session(db, p.id, NOW - timedelta(days=1),
                          {"left": {"n": 3, "peak_swing_flexion_deg": [50, 56, 53]}})
        # The newest session's strides are all low quality: it has no value, so the one before stays the latest.
        add_session(db, p.id, NOW, {"left": {"n": 3, "peak_swing_flexion_deg": 90.0, "quality": 0.2}})
        db.commit()
        latest = service.latest_session_means(db, [p.id, other.id], ("peak_swing_flexion_deg", "rom_deg"))
        assert set(latest) == {p.id}  # the other patient has no session
        left, right = latest[p.id]["left"], latest[p.id]["right"]
        assert left["peak_swing_flexion_deg"]["mean"] == pytest.approx(53.0)
        assert left["peak_swing_flexion_deg"]["at"] == NOW - timedelta(days=1)
        assert left["rom_deg"]["mean"] == pytest.approx(51.0)  # rom = peak - 2 deg minimum flexion
        assert right["peak_swing_flexion_deg"]["mean"] == pytest.approx(61.0)
        assert service.latest_session_means(db, [], ("rom_deg",)) == {}
        medians = service.session_medians(db, [old, new], "peak_swing_flexion_deg")
        # 150 deg is implausible: three of the four left strides count, their median is 42.
        assert medians == {old: {"left": (3, 42.0), "right": (3, 61.0)}, new: {"left": (3, 53.0)}}
        assert service.session_medians(db, [], "peak_swing_flexion_deg") == {}


def test_latest_means_and_session_medians_never_pool_or_mix_activities(factory) -> None:
    with factory() as db:
        p = _patient(db)
        walk = add_session(db, p.id, NOW - timedelta(days=1), {"left": {"n": 3, "peak_swing_flexion_deg": 60.0}})
        # A later session uploaded as `unknown`: walking and running strides in one session, running listed first.
        mixed = add_session(db, p.id, NOW, {"left": {
            "n": 6, "peak_swing_flexion_deg": [80, 80, 80, 55, 55, 55],
            "activity": ["running"] * 3 + ["walking"] * 3}})
        db.commit()
        latest = service.latest_session_means(db, [p.id], ("peak_swing_flexion_deg",))
        assert latest[p.id]["left"]["peak_swing_flexion_deg"] == {"mean": pytest.approx(55.0), "at": NOW}
        running = service.latest_session_means(db, [p.id], ("peak_swing_flexion_deg",), activity="running")
        assert running[p.id]["left"]["peak_swing_flexion_deg"]["mean"] == pytest.approx(80.0)
        medians = service.session_medians(db, [walk, mixed], "peak_swing_flexion_deg")
        assert medians == {walk: {"left": (3, 60.0)}, mixed: {"left": (3, 55.0)}}


def test_numbered_session_pages_and_the_first_processed_session(factory) -> None:
    from server.patients import service as patient_service

    with factory() as db:
        p = _patient(db)
        add_session(db, p.id, NOW - timedelta(days=9), {"left": {"n": 3}}, status="failed", refresh=False)
        ids = [add_session(db, p.id, NOW - timedelta(days=d), {"left": {"n": 3}}) for d in (5, 3, 1)]
        db.commit()
        first = patient_service.first_done_session(db, p.id)
        assert first is not None and first.id == ids[0]  # the failed session before it is not a reference
        page = patient_service.session_page(db, p.id, offset=1, limit=2)
        assert page.total == 4 and [s.id for s in page.items] == [ids[1], ids[0]]  # newest first
        assert patient_service.first_done_session(db, _patient(db).id) is None


def test_gait_cycle_of_a_session_without_a_trace_reads_no_strides(factory) -> None:
    from sqlalchemy import event

    from server.results import service as results_service

    with factory() as db:
        p = _patient(db)
        sid = add_session(db, p.id, NOW, {"left": {"n": 50}})
        db.commit()
        statements: list[str] = []
        engine = db.get_bind()

        def record(conn, cursor, statement, *args) -> None:  # noqa: ANN001, ANN002
            statements.append(statement)

        event.listen(engine, "before_cursor_execute", record)
        try:
            assert results_service.gait_cycles(db, sid) == {}
        finally:
            event.remove(engine, "before_cursor_execute", record)
        assert statements and all("knee_angle_traces" in s for s in statements)
        assert len(results_service.strides(db, sid)) == 50  # the strides are there, only not read for nothing
