"""A small cohort through the whole system: simulated sessions uploaded through the API, processed by the job runner,
and the attention list flags the clear decline and leaves the stable patient alone (bench/cohort.py at full size)."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime

import pytest

from bench.cohort import PlannedSession, _simulate
from server.config import Settings
from server.processing.jobs import run_queued
from tests.server.helpers import Api, bearer, open_api

NOW = datetime.now(UTC).replace(microsecond=0)
DAYS = [20.0, 15.0, 10.0, 5.0, 0.5]
TRAJECTORIES = {"declining": (64.0, 46.0), "stable": (64.0, 64.0)}


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


@pytest.fixture(scope="module")
def simulated() -> dict[str, list[tuple[dict, list[dict]]]]:
    out: dict[str, list[tuple[dict, list[dict]]]] = {}
    for p_i, (name, (start, end)) in enumerate(TRAJECTORIES.items()):
        for k, d in enumerate(DAYS):
            peak = start + (end - start) * k / (len(DAYS) - 1)
            s = PlannedSession(p_i, k, 7000 + 10 * p_i + k, d, peak, "normal", 0.02, None, duration_s=35.0,
                               legs=("left",))
            _, _, create, batches = _simulate(s, NOW.isoformat())
            out.setdefault(name, []).append((create, batches))
    return out


def test_a_clear_decline_is_flagged_and_a_stable_patient_is_not(api: Api, simulated: dict) -> None:
    _, clin = api.clinician()
    ids = {}
    for name, sessions in simulated.items():
        patient = api.patient(clin, affected_leg="left", display_name=name, prescribed_sessions_per_week=2)
        ids[name] = patient["id"]
        dev = api.device(clin, patient["id"])
        for create, batches in sessions:
            r = api.client.post("/v1/sessions", json={**create, "patient_id": patient["id"]}, headers=bearer(dev))
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            for b in batches:
                assert api.upload(dev, sid, b).status_code == 201
            assert api.client.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    assert run_queued(api.client.app.state.sessionmaker) == 10  # type: ignore[attr-defined]

    r = api.client.get("/v1/attention", headers=bearer(clin))
    assert r.status_code == 200, r.text
    body = r.json()
    flags = {it["patient"]["id"]: [f["kind"] for f in it["flags"]] for it in body["items"]}
    assert flags.get(ids["declining"]) == ["declining"]
    assert ids["stable"] not in flags
    decline = body["items"][0]["flags"][0]
    assert decline["fitted_change"] < -decline["mdc"] and decline["p_value"] < body["params"]["alpha"]
    assert body["rules"]["preset"] == "default" and "one-sided t-test" in body["rules"]["declining"]["method"]
    # The thresholds are the clinic's: a named preset, echoed back.
    strict = api.client.get("/v1/attention", params={"preset": "conservative"}, headers=bearer(clin)).json()
    assert strict["params"]["preset"] == "conservative" and strict["params"]["alpha"] == 0.001
    assert api.client.get("/v1/attention", params={"preset": "nope"}, headers=bearer(clin)).status_code == 422


def test_the_cohort_bench_runs_both_upload_paths_and_prints_its_tables(capsys: pytest.CaptureFixture[str]) -> None:
    from bench.cohort import main, plan

    patients, sessions = plan("tune", 2, ["stable"], api_per_group=1)
    assert [p.via_api for p in patients] == [True, False] and len(sessions) == 16
    main(["--split", "tune", "--per-group", "2", "--api-per-group", "1", "--groups", "stable", "--workers", "1"])
    out = capsys.readouterr().out
    assert "1 patients uploaded through the API" in out
    rows = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| ")}
    # Both stable patients are listed in the per-group table, processed from either path, and none is flagged.
    assert rows["stable"].replace(" ", "") == "|stable|2|0|0|0|0|0|"
    assert "stable patients (0-5 % loss) with declining or sensor_trouble: 0 of 2" in out
