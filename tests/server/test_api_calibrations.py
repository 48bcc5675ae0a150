"""Knee calibrations over HTTP: record/list/delete, who may do what, validation, and processing that uses the
calibration valid at the session's start (and says so), on SQLite and PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from pipeline.params import WALKING
from pipeline.simulate import SimConfig, simulate_session
from server.calibrations.routes import AFFECTED_HEADER
from server.calibrations.service import valid_at
from server.config import Settings
from server.processing.jobs import run_queued
from server.simulate_cli import session_to_requests
from tests.server.helpers import Api, bearer, count_rows, open_api

NOW = datetime.now(UTC).replace(microsecond=0)
# The simulated session starts ten days ago; calibrations are placed around that instant.
SESSION_START = NOW - timedelta(days=10)


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def body(leg: str = "left", deg: float = 8.0, measured_at: datetime | str | None = None,
         **extra: Any) -> dict[str, Any]:
    when = measured_at if measured_at is not None else SESSION_START - timedelta(days=1)
    return {"leg": leg, "standing_knee_deg": deg, "method": "goniometer",
            "measured_at": when if isinstance(when, str) else when.isoformat(), **extra}


def url(patient_id: str, calibration_id: str = "") -> str:
    return f"/v1/patients/{patient_id}/calibrations" + (f"/{calibration_id}" if calibration_id else "")


def test_create_list_get_delete(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    pid = patient["id"]
    berlin = (SESSION_START - timedelta(days=3)).astimezone(UTC).replace(tzinfo=None).isoformat() + "+01:00"
    first = c.post(url(pid), json=body("left", 6.5, berlin, note="goniometer, supine -> standing"),
                   headers=bearer(clin))
    assert first.status_code == 201, first.text
    got = first.json()
    assert got["leg"] == "left" and got["standing_knee_deg"] == 6.5 and got["method"] == "goniometer"
    assert got["note"] == "goniometer, supine -> standing" and got["patient_id"] == pid
    # stored and answered in UTC: the +01:00 instant is one hour earlier in UTC
    measured = datetime.fromisoformat(got["measured_at"])
    assert measured.utcoffset() == timedelta(0)
    assert measured == datetime.fromisoformat(berlin)
    assert got["affected_sessions"] == 0 and got["affected_session_ids"] == []
    right = c.post(url(pid), json=body("right", -3.0, method="guided_trial"), headers=bearer(clin)).json()
    newer = c.post(url(pid), json=body("left", 11.0, SESSION_START), headers=bearer(clin)).json()
    assert right["method"] == "guided_trial" and right["standing_knee_deg"] == -3.0

    listed = c.get(url(pid), headers=bearer(clin)).json()
    assert [x["id"] for x in listed["items"]] == [newer["id"], right["id"], got["id"]]  # newest measurement first
    assert listed["next_cursor"] is None
    assert "affected_sessions" not in listed["items"][0]
    lefts = c.get(url(pid) + "?leg=left", headers=bearer(clin)).json()["items"]
    assert [x["id"] for x in lefts] == [newer["id"], got["id"]]
    assert c.get(url(pid) + "?leg=both", headers=bearer(clin)).status_code == 422
    # keyset pages walk every calibration once
    seen, cursor = [], None
    while True:
        page = c.get(url(pid) + "?limit=1" + (f"&cursor={cursor}" if cursor else ""), headers=bearer(clin)).json()
        seen += [x["id"] for x in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == [x["id"] for x in listed["items"]]
    assert c.get(url(pid) + "?cursor=garbage", headers=bearer(clin)).status_code == 400

    one = c.get(url(pid, right["id"]), headers=bearer(clin))
    assert one.status_code == 200 and one.json() == listed["items"][1]
    r = c.delete(url(pid, right["id"]), headers=bearer(clin))
    assert r.status_code == 204 and r.headers[AFFECTED_HEADER] == "0" and r.content == b""
    assert c.get(url(pid, right["id"]), headers=bearer(clin)).status_code == 404
    r = c.delete(url(pid, right["id"]), headers=bearer(clin))
    assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
    assert [x["id"] for x in c.get(url(pid), headers=bearer(clin)).json()["items"]] == [newer["id"], got["id"]]

    # Deleting the patient deletes its calibrations.
    assert count_rows(api.engine)["knee_calibrations"] == 2
    assert c.delete(f"/v1/patients/{pid}", headers=bearer(clin)).status_code == 204
    assert count_rows(api.engine)["knee_calibrations"] == 0


def test_access_rules(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    _, other = api.clinician("Dr. Other")
    patient = api.patient(clin)
    pid = patient["id"]
    dev = api.device(clin, pid)
    stranger_patient = api.patient(other)
    stranger_dev = api.device(other, stranger_patient["id"])
    cal = c.post(url(pid), json=body(), headers=bearer(clin)).json()
    theirs = c.post(url(stranger_patient["id"]), json=body(), headers=bearer(other)).json()

    assert c.get(url(pid)).status_code == 401
    # another clinician's patient does not exist for the caller, exactly like the other patient routes
    for method, path, kwargs in (("get", url(pid), {}), ("post", url(pid), {"json": body()}),
                                 ("get", url(pid, cal["id"]), {}), ("delete", url(pid, cal["id"]), {})):
        r = c.request(method, path, headers=bearer(other), **kwargs)
        assert r.status_code == 404, (method, path, r.text)
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.json()["detail"] == "Patient not found"
    assert c.get(url(stranger_patient["id"]), headers=bearer(dev)).status_code == 404
    # a calibration of another patient is not found under one's own patient
    assert c.get(url(pid, theirs["id"]), headers=bearer(clin)).status_code == 404
    assert c.delete(url(pid, theirs["id"]), headers=bearer(clin)).status_code == 404

    # the patient's device reads, never writes
    assert [x["id"] for x in c.get(url(pid), headers=bearer(dev)).json()["items"]] == [cal["id"]]
    assert c.get(url(pid, cal["id"]), headers=bearer(dev)).status_code == 200
    r = c.post(url(pid), json=body(), headers=bearer(dev))
    assert r.status_code == 403 and r.json()["type"].endswith(":forbidden")
    assert c.delete(url(pid, cal["id"]), headers=bearer(dev)).status_code == 403
    assert c.delete(url(stranger_patient["id"], theirs["id"]), headers=bearer(dev)).status_code == 403
    assert c.get(url(pid), headers=bearer(stranger_dev)).status_code == 404

    # an admin may do everything
    r = c.post(url(pid), json=body("right"), headers=bearer(api.admin))
    assert r.status_code == 201
    assert c.delete(url(pid, r.json()["id"]), headers=bearer(api.admin)).status_code == 204
    assert [x["id"] for x in c.get(url(pid), headers=bearer(clin)).json()["items"]] == [cal["id"]]


@pytest.mark.parametrize(("bad", "field"), [
    ({"standing_knee_deg": 60.5}, "standing_knee_deg"),
    ({"standing_knee_deg": -20.5}, "standing_knee_deg"),
    ({"standing_knee_deg": "eight"}, "standing_knee_deg"),
    ({"standing_knee_deg": None}, "standing_knee_deg"),
    ({"measured_at": "2026-11-01T10:00:00"}, "measured_at"),  # no offset: which instant is it?
    ({"measured_at": "yesterday"}, "measured_at"),
    ({"measured_at": (NOW + timedelta(days=2)).isoformat()}, "measured_at"),
    ({"measured_at": "0001-01-01T00:00:00+14:00"}, "measured_at"),  # before the calendar's first UTC instant
    ({"measured_at": "0001-01-01T00:00:00+00:00"}, "measured_at"),  # a patient's local day of it would overflow
    ({"measured_at": 0}, "measured_at"),  # seconds since 1970 is a client bug, not a measurement date
    ({"standing_knee_deg": True}, "standing_knee_deg"),  # a boolean is not a number
    ({"standing_knee_deg": "5"}, "standing_knee_deg"),
    ({"method": "eyeballed"}, "method"),
    ({"leg": "both"}, "leg"),
    ({"note": "bad\u0000note"}, "note"),
    ({"note": "x" * 2001}, "note"),
    ({"unexpected": 1}, "unexpected"),
])
def test_invalid_bodies_are_422_problems_and_store_nothing(api: Api, bad: dict[str, Any], field: str) -> None:
    c = api.client
    _, clin = api.clinician()
    pid = api.patient(clin)["id"]
    r = c.post(url(pid), json={**body(), **bad}, headers=bearer(clin))
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["errors"][0]["field"] == field
    assert c.get(url(pid), headers=bearer(clin)).json()["items"] == []


def test_unencodable_text_and_odd_ids_are_problems_not_500(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    pid = api.patient(clin)["id"]
    headers = {**bearer(clin), "Content-Type": "application/json"}
    for raw in ('{"leg": "left", "standing_knee_deg": NaN, "method": "goniometer", '
                '"measured_at": "2026-01-01T00:00:00Z"}',
                '{"leg": "left", "standing_knee_deg": 5, "method": "goniometer", '
                '"measured_at": "2026-01-01T00:00:00Z", "note": "lone \\ud800 surrogate"}',
                '{"leg": "left", "standing_knee_deg": 5, "method": "goniometer", '
                '"measured_at": "2026-01-01T00:00:00Z", "note": "nul \\u0000 escaped"}',
                "not json"):
        r = c.post(url(pid), content=raw, headers=headers)
        assert r.status_code == 422, (raw, r.text)
        assert r.headers["content-type"].startswith("application/problem+json")
    for odd in ("x" * 300, "%F0%9F%A6%B5"):
        assert c.get(url(pid, odd), headers=bearer(clin)).status_code == 404
        assert c.delete(url(pid, odd), headers=bearer(clin)).status_code == 404
    # PostgreSQL text cannot hold NUL: a NUL anywhere in the path is refused before any query (422 problem)
    for r in (c.get(url(pid, "%00"), headers=bearer(clin)), c.delete(url(pid, "%00"), headers=bearer(clin)),
              c.get(url("%00"), headers=bearer(clin)), c.post(url("%00"), json=body(), headers=bearer(clin))):
        assert r.status_code == 422 and r.headers["content-type"].startswith("application/problem+json")
    assert c.get("/v1/sessions/%00", headers=bearer(clin)).status_code == 422
    assert c.get(url(pid), headers=bearer(clin)).json()["items"] == []


def test_the_latest_calibration_measured_at_or_before_the_start_applies() -> None:
    start = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)

    def cal(cid: str, measured: datetime, created: datetime | None = None) -> SimpleNamespace:
        return SimpleNamespace(id=cid, measured_at=measured, created_at=created or measured)

    old = cal("old", start - timedelta(days=30))
    recent = cal("recent", start - timedelta(days=2))
    exact = cal("exact", start)
    later = cal("later", start + timedelta(seconds=1))
    assert valid_at([old, later, recent], start).id == "recent"
    assert valid_at([old, recent, exact, later], start).id == "exact"  # measured at the very start: applies
    assert valid_at([later], start) is None  # measured after the session: does not rewrite it
    assert valid_at([], start) is None
    # SQLite hands back naive UTC times; they compare like aware ones
    assert valid_at([cal("naive", (start - timedelta(hours=1)).replace(tzinfo=None))], start).id == "naive"
    # two measurements of the same instant: the one recorded last wins
    twin_a = cal("a", start - timedelta(days=1), start)
    twin_b = cal("b", start - timedelta(days=1), start + timedelta(minutes=1))
    assert valid_at([twin_b, twin_a], start).id == "b"


STAND_KNEE_DEG = 12.0  # a flexion contracture the assumed standing flexion does not know about


def _upload_simulated(api: Api, clin: str, dev: str, pid: str) -> tuple[str, float]:
    """A processed-ready simulated session that stands at STAND_KNEE_DEG; returns its id and true median peak."""
    sim = simulate_session(SimConfig(n_strides=24, seed=3, legs=("left",), stand_knee_deg=STAND_KNEE_DEG))
    create, batches = session_to_requests(sim, batch_size=400, patient_id=pid, started_at=SESSION_START,
                                          client_session_id="contracture-1")
    sid = api.client.post("/v1/sessions", json=create, headers=bearer(dev)).json()["id"]
    for b in batches:
        assert api.upload(dev, sid, b).status_code in (200, 201)
    assert api.client.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    truth = float(np.median([s.peak_swing_flexion_deg for s in sim.truth["left"].strides if s.steady]))
    return sid, truth


def _processed(api: Api, clin: str, sid: str) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    assert run_queued(api.client.app.state.sessionmaker) == 1  # type: ignore[attr-defined]
    sess = api.client.get(f"/v1/sessions/{sid}", headers=bearer(clin)).json()
    assert sess["status"] == "done", sess["error"]
    strides = api.client.get(f"/v1/sessions/{sid}/strides?leg=left", headers=bearer(clin)).json()["strides"]
    assert len(strides) >= 15
    return sess, strides


def _used_id(api: Api, token: str, sid: str) -> str | None:
    """The id of the calibration the session's left leg was processed with, as GET /v1/sessions/{id} says."""
    block = api.client.get(f"/v1/sessions/{sid}", headers=bearer(token)).json()["summary"]["calibration"]["left"]
    return None if block is None else block["id"]


def _median_peak(strides: list[dict[str, Any]]) -> float:
    return float(np.median([s["peak_swing_flexion_deg"] for s in strides]))


def test_processing_applies_the_calibration_valid_at_the_start_and_says_so(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    pid = api.patient(clin)["id"]
    dev = api.device(clin, pid)
    sid, truth = _upload_simulated(api, clin, dev, pid)

    # Measured after the session: it does not apply to it, now or on reprocess.
    late = c.post(url(pid), json=body("left", STAND_KNEE_DEG, SESSION_START + timedelta(hours=2)),
                  headers=bearer(clin)).json()
    sess, assumed = _processed(api, clin, sid)
    diag = sess["summary"]["legs"]["left"]["diagnostics"]
    assert diag["level_source"] == "assumed" and diag["calibration_id"] is None
    assert diag["standing_knee_deg"] == WALKING.posture.standing_knee_deg
    assert sess["summary"]["calibration"] == {"left": None}

    # A calibration valid at the start: reported as affecting the processed session, which is not reprocessed.
    r = c.post(url(pid), json=body("left", STAND_KNEE_DEG, SESSION_START - timedelta(days=5), method="guided_trial"),
               headers=bearer(clin))
    cal = r.json()
    assert r.status_code == 201 and cal["affected_sessions"] == 1 and cal["affected_session_ids"] == [sid]
    right = c.post(url(pid), json=body("right", 3.0), headers=bearer(clin)).json()
    assert right["affected_sessions"] == 0  # the session has no right leg results
    unchanged = c.get(f"/v1/sessions/{sid}", headers=bearer(clin)).json()
    assert unchanged["summary"] == sess["summary"] and unchanged["status"] == "done"

    assert c.post(f"/v1/sessions/{sid}/reprocess", headers=bearer(clin)).status_code == 202
    sess, calibrated = _processed(api, clin, sid)
    diag = sess["summary"]["legs"]["left"]["diagnostics"]
    assert diag["level_source"] == "calibration" and diag["calibration_id"] == cal["id"] != late["id"]
    assert diag["standing_knee_deg"] == STAND_KNEE_DEG
    assert sess["summary"]["calibration"] == {"left": {
        "id": cal["id"], "standing_knee_deg": STAND_KNEE_DEG, "method": "guided_trial",
        "measured_at": cal["measured_at"].replace("+00:00", "Z")}}
    # The calibrated level is closer to the simulated truth than the assumed one.
    err_assumed, err_calibrated = _median_peak(assumed) - truth, _median_peak(calibrated) - truth
    assert abs(err_calibrated) < abs(err_assumed) - 3.0, (err_assumed, err_calibrated)
    assert abs(err_calibrated) < 3.0
    # Re-creating the same state reports nothing to do; the device reads which calibration was used.
    assert _used_id(api, dev, sid) == cal["id"]
    again = c.post(url(pid), json=body("left", STAND_KNEE_DEG, SESSION_START + timedelta(days=1)),
                   headers=bearer(clin)).json()
    assert again["affected_sessions"] == 0
    assert c.delete(url(pid, again["id"]), headers=bearer(clin)).headers[AFFECTED_HEADER] == "0"

    # The comparison re-runs the pipeline with the same calibration as the stored results.
    cmp = c.get(f"/v1/sessions/{sid}/compare?estimators=auto", headers=bearer(clin)).json()
    auto = cmp["legs"]["left"]["estimators"]["auto"]
    assert auto["n_strides"] == len(calibrated)
    assert auto["peak_swing_flexion_deg"]["median"] == pytest.approx(_median_peak(calibrated), abs=0.01)

    # Deleting it: the session keeps what it was processed with until it is reprocessed.
    r = c.delete(url(pid, cal["id"]), headers=bearer(clin))
    assert r.status_code == 204 and r.headers[AFFECTED_HEADER] == "1"
    assert _used_id(api, clin, sid) == cal["id"]
    assert c.post(f"/v1/sessions/{sid}/reprocess", headers=bearer(clin)).status_code == 202
    sess, back = _processed(api, clin, sid)
    assert sess["summary"]["legs"]["left"]["diagnostics"]["level_source"] == "assumed"
    assert sess["summary"]["calibration"] == {"left": None}
    assert _median_peak(back) == pytest.approx(_median_peak(assumed), abs=1e-6)
    cmp = c.get(f"/v1/sessions/{sid}/compare?estimators=auto", headers=bearer(clin)).json()
    assert cmp["legs"]["left"]["estimators"]["auto"]["peak_swing_flexion_deg"]["median"] == pytest.approx(
        _median_peak(back), abs=0.01)
