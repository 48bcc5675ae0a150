"""Sessions: creation and its validation, idempotent retry per client_session_id, status and reprocess rules."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from datetime import datetime

import pytest

from server.config import Settings
from tests.server.helpers import SENSORS_LEFT, Api, batch_body, bearer, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def _body(patient_id: str, **changes: object) -> dict:
    body = {"patient_id": patient_id, "client_session_id": "app-uuid-1", "started_at": "2026-11-21T09:30:00+00:00",
            "activity": "walking", "sensors": copy.deepcopy(SENSORS_LEFT)}
    body.update(changes)
    return body


def test_create_and_retry_returns_same_session(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    r = c.post("/v1/sessions", json=_body(patient["id"], started_at="2026-11-21T10:30:00+01:00"),
               headers=bearer(dev))
    assert r.status_code == 201
    s = r.json()
    assert s["status"] == "receiving" and s["patient_id"] == patient["id"] and s["error"] is None
    assert datetime.fromisoformat(s["started_at"]) == datetime.fromisoformat("2026-11-21T09:30:00+00:00")
    assert {x["sensor_id"] for x in s["sensors"]} == {"L-thigh", "L-shank"}
    assert s["received"]["L-thigh"] == {"batches": 0, "samples": 0, "gaps": 0, "gap_s": 0.0, "first_t_s": None,
                                        "last_t_s": None, "missing_seq": [],
                                        "observed_rate_hz": None}
    r2 = c.post("/v1/sessions", json=_body(patient["id"]), headers=bearer(dev))
    assert datetime.fromisoformat(r2.json()["started_at"]) == datetime.fromisoformat("2026-11-21T09:30:00Z")
    assert r2.status_code == 200 and r2.json()["id"] == s["id"]
    # Same client id with other sensors: a client bug, not a retry.
    other = _body(patient["id"], sensors=[dict(SENSORS_LEFT[0], sample_rate_hz=50)])
    assert c.post("/v1/sessions", json=other, headers=bearer(dev)).status_code == 409
    # The same client id for another patient is another session.
    p2 = api.patient(clin)
    r3 = c.post("/v1/sessions", json=_body(p2["id"]), headers=bearer(clin))
    assert r3.status_code == 201 and r3.json()["id"] != s["id"]
    assert c.get(f"/v1/sessions/{s['id']}", headers=bearer(clin)).json()["id"] == s["id"]


def _sensor(**changes: object) -> list[dict]:
    return [dict(SENSORS_LEFT[0], **changes)]


INVALID = {
    "duplicate sensor_id": {"sensors": [SENSORS_LEFT[0], dict(SENSORS_LEFT[1], sensor_id="L-thigh")]},
    "two sensors on one segment": {"sensors": [SENSORS_LEFT[0], dict(SENSORS_LEFT[0], sensor_id="other")]},
    "rate 0": {"sensors": _sensor(sample_rate_hz=0)},
    "rate 5000": {"sensors": _sensor(sample_rate_hz=5000)},
    "bad gyro unit": {"sensors": _sensor(gyro_unit="rpm")},
    "bad acc unit": {"sensors": _sensor(acc_unit="ft/s2")},
    "bad leg": {"sensors": _sensor(leg="middle")},
    "bad segment": {"sensors": _sensor(segment="foot")},
    "no sensors": {"sensors": []},
    "bad activity": {"activity": "swimming"},
    "naive started_at": {"started_at": "2026-11-21T09:30:00"},
    "empty client id": {"client_session_id": ""},
}


@pytest.mark.parametrize("case", sorted(INVALID))
def test_invalid_session_bodies_get_422(api: Api, case: str) -> None:
    _, clin = api.clinician()
    patient = api.patient(clin)
    r = api.client.post("/v1/sessions", json=_body(patient["id"], **INVALID[case]), headers=bearer(clin))
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json") and r.json()["errors"]
    listed = api.client.get(f"/v1/patients/{patient['id']}/sessions", headers=bearer(clin)).json()
    assert listed["items"] == []


def test_reprocess_rules(api: Api) -> None:
    c = api.client
    clin, dev, sess = api.setup_device_session()
    sid = sess["id"]
    # Not completed yet: nothing to reprocess.
    assert c.post(f"/v1/sessions/{sid}/reprocess", headers=bearer(clin)).status_code == 409
    assert api.upload(dev, sid, batch_body("L-thigh", 0)).status_code == 201
    assert c.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    # Already queued: 202 with the current state, nothing changes.
    r = c.post(f"/v1/sessions/{sid}/reprocess", headers=bearer(api.admin))
    assert r.status_code == 202 and r.json()["status"] == "queued"


def test_session_list_is_newest_first_and_paginated(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    ids = []
    for day in range(1, 6):
        body = _body(patient["id"], client_session_id=f"c{day}", started_at=f"2026-11-0{day}T08:00:00+00:00")
        ids.append(c.post("/v1/sessions", json=body, headers=bearer(clin)).json()["id"])
    first = c.get(f"/v1/patients/{patient['id']}/sessions?limit=2", headers=bearer(clin)).json()
    assert [s["id"] for s in first["items"]] == ids[::-1][:2]
    rest = c.get(f"/v1/patients/{patient['id']}/sessions?limit=10&cursor={first['next_cursor']}",
                 headers=bearer(clin)).json()
    assert [s["id"] for s in rest["items"]] == ids[::-1][2:] and rest["next_cursor"] is None
