"""Issue 4 "done when": simulated sessions a week apart with rising peak flexion, through upload, the job runner
and the pipeline, give rising day buckets, a positive slope and a significant change."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import pytest

from pipeline.simulate import SimConfig, simulate_session
from server.config import Settings
from server.processing.jobs import run_queued
from server.simulate_cli import session_to_requests
from tests.server.helpers import Api, bearer, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def test_rising_peak_flexion_over_three_weekly_sessions(api: Api) -> None:
    _, clin = api.clinician()
    # Los Angeles is UTC-7 in October: 07:30 UTC is 00:30 local, just after local midnight.
    patient = api.patient(clin, affected_leg="left", timezone="America/Los_Angeles")
    dev = api.device(clin, patient["id"])
    t0 = datetime(2026, 10, 5, 7, 30, tzinfo=UTC)
    truths = []
    # Normative shapes with peak swing flexion ~37 (stiff knee), ~54 (slow) and ~61 deg (normal).
    for week, pattern in enumerate(["stiff-knee", "slow", "normal"]):
        sim = simulate_session(SimConfig(pattern=pattern, seed=week + 1, n_strides=60, legs=("left",)))
        truths.append(sim)
        create, batches = session_to_requests(sim, batch_size=1000, patient_id=patient["id"],
                                              started_at=t0 + timedelta(days=7 * week))
        r = api.client.post("/v1/sessions", json=create, headers=bearer(dev))
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        for body in batches:
            assert api.upload(dev, sid, body).status_code == 201
        assert api.client.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    assert run_queued(api.client.app.state.sessionmaker) == 3  # type: ignore[attr-defined]

    r = api.client.get(f"/v1/patients/{patient['id']}/trends",
                       params={"metric": "peak_swing_flexion_deg", "bucket": "day"}, headers=bearer(clin))
    assert r.status_code == 200, r.text
    body = r.json()
    buckets = body["buckets"]
    assert [b["start"] for b in buckets] == ["2026-10-05T00:00:00-07:00", "2026-10-12T00:00:00-07:00",
                                             "2026-10-19T00:00:00-07:00"]
    means = [b["mean"] for b in buckets]
    assert means[0] < means[1] < means[2], means
    assert all(b["n_strides"] >= 20 for b in buckets)
    # Three points leave one residual degree of freedom (t = 12.7), so only the slope's sign is asserted.
    assert body["trend"]["slope_per_week"] > 0 and body["trend"]["n"] == 3
    change = body["change"]
    assert change["significant"] is True and change["direction"] == "improved"
    assert change["delta"] > change["mdc"] == 5.0
    # The estimate follows the simulator's ground truth within the estimator's error (Allseits: 5-7 deg RMSE).
    for b, sim in zip(buckets, truths, strict=True):
        true = [s.peak_swing_flexion_deg for s in sim.truth["left"].strides if s.steady]
        assert b["median"] == pytest.approx(sorted(true)[len(true) // 2], abs=7.0)


def test_a_patient_who_runs_is_not_flagged_for_sensor_trouble_and_runs_never_pool_with_walks(api: Api) -> None:
    """Running strides come from the running path's primary estimator: they are no fallback, and they form a
    trend of their own (the walking trend of a patient who only runs is empty)."""
    _, clin = api.clinician()
    patient = api.patient(clin, affected_leg="left")
    dev = api.device(clin, patient["id"])
    now = datetime.now(UTC).replace(microsecond=0)
    for day in (3, 1):
        sim = simulate_session(SimConfig(pattern="running", seed=day, n_strides=60, legs=("left",)))
        create, batches = session_to_requests(sim, batch_size=1000, patient_id=patient["id"],
                                              started_at=now - timedelta(days=day))
        r = api.client.post("/v1/sessions", json=create, headers=bearer(dev))
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        for body in batches:
            assert api.upload(dev, sid, body).status_code == 201
        assert api.client.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    assert run_queued(api.client.app.state.sessionmaker) == 2  # type: ignore[attr-defined]
    strides = api.client.get(f"/v1/sessions/{sid}/strides", headers=bearer(clin)).json()
    n_running = len(strides["strides"] if isinstance(strides, dict) else strides)
    assert n_running >= 50

    attention = api.client.get("/v1/attention", headers=bearer(clin))
    assert attention.status_code == 200, attention.text
    flags = {f["kind"] for it in attention.json()["items"] if it["patient"]["id"] == patient["id"]
             for f in it["flags"]}
    assert "sensor_trouble" not in flags

    def trend(**params: str) -> dict:
        r = api.client.get(f"/v1/patients/{patient['id']}/trends",
                           params={"metric": "peak_swing_flexion_deg", "bucket": "day", **params},
                           headers=bearer(clin))
        assert r.status_code == 200, r.text
        return r.json()

    assert sum(b["n_strides"] for b in trend()["buckets"]) == 0
    running = trend(activity="running")
    assert running["activity"] == "running"
    assert sum(b["n_strides"] for b in running["buckets"]) >= 100
