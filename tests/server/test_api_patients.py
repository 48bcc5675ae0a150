"""Patients: creation rules, keyset pagination, and deletion of every row that belongs to a patient."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime

import numpy as np
import pytest

from server.codec import encode_trace
from server.config import Settings
from server.results.models import KneeAngleTrace, Stride
from tests.server.helpers import Api, batch_body, bearer, count_rows, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def test_create_patient_fields_and_validation(api: Api) -> None:
    c = api.client
    clin_id, clin = api.clinician()
    p = api.patient(clin, external_id="MRN-1", display_name="P. One", affected_leg="left", timezone="Europe/Berlin")
    assert p["clinician_id"] == clin_id and p["affected_leg"] == "left" and p["timezone"] == "Europe/Berlin"
    assert datetime.fromisoformat(p["created_at"]).utcoffset() is not None
    assert c.get(f"/v1/patients/{p['id']}", headers=bearer(clin)).json() == p
    for bad in ({"affected_leg": "both"}, {"timezone": "Mars/Olympus"}, {"unknown_field": 1}):
        r = c.post("/v1/patients", json=bad, headers=bearer(clin))
        assert r.status_code == 422, bad
        assert r.json()["errors"][0]["field"]
    # Admin may assign a clinician, but only an existing one; a clinician may not assign another.
    other_id, _ = api.clinician("Other")
    r = c.post("/v1/patients", json={"clinician_id": other_id}, headers=bearer(api.admin))
    assert r.status_code == 201 and r.json()["clinician_id"] == other_id
    assert c.post("/v1/patients", json={"clinician_id": "nope"}, headers=bearer(api.admin)).status_code == 422
    assert c.post("/v1/patients", json={"clinician_id": other_id}, headers=bearer(clin)).status_code == 422


def test_pagination_walks_every_patient_once_in_creation_order(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    _, other = api.clinician("Other")
    created = [api.patient(clin, display_name=f"p{i}")["id"] for i in range(7)]
    api.patient(other)
    seen: list[str] = []
    cursor = None
    pages = 0
    while True:
        url = "/v1/patients?limit=3" + (f"&cursor={cursor}" if cursor else "")
        page = c.get(url, headers=bearer(clin)).json()
        assert len(page["items"]) <= 3
        seen += [p["id"] for p in page["items"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == created and pages == 3
    assert len(c.get("/v1/patients", headers=bearer(clin)).json()["items"]) == 7  # default limit 50
    assert c.get("/v1/patients?limit=201", headers=bearer(clin)).status_code == 422
    assert c.get("/v1/patients?limit=0", headers=bearer(clin)).status_code == 422
    r = c.get("/v1/patients?cursor=garbage!", headers=bearer(clin))
    assert r.status_code == 400 and r.json()["errors"][0]["field"] == "cursor"


def test_search_finds_own_patients_by_external_id_literally(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    _, other = api.clinician("Other")
    knee = api.patient(clin, external_id="KNEE-042")["id"]
    api.patient(clin, external_id="HIP-7")
    under = api.patient(clin, external_id="a_b")["id"]
    api.patient(clin, external_id="axb")
    api.patient(other, external_id="knee-043")  # someone else's: never listed

    def ids(search: str) -> list[str]:
        r = c.get("/v1/patients", params={"search": search}, headers=bearer(clin))
        assert r.status_code == 200, r.text
        return [p["id"] for p in r.json()["items"]]

    assert ids("knee") == [knee]
    assert ids("a_b") == [under]  # "_" is a character, not a wildcard
    assert ids("%") == []
    assert len(ids("")) == 4
    assert c.get("/v1/patients", params={"search": "x" * 101}, headers=bearer(clin)).status_code == 422


def _fill_patient(api: Api, clin: str) -> str:
    """A patient with sessions, batches, sensors, a device token, strides and a knee angle trace."""
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    for k in range(2):
        sess = api.session(dev, patient["id"], client_session_id=f"s{k}")
        for q in range(3):
            assert api.upload(dev, sess["id"], batch_body("L-shank", q)).status_code == 201
        with api.client.app.state.sessionmaker() as db:  # type: ignore[attr-defined]
            for i in range(4):
                db.add(Stride(session_id=sess["id"], patient_id=patient["id"], leg="left", index=i,
                              started_at=datetime.now(UTC), t_start_s=i, t_end_s=i + 1.0, duration_s=1.0,
                              t_toe_off_s=i + 0.6, stance_time_s=0.6, swing_time_s=0.4, stance_pct=60.0,
                              peak_swing_flexion_deg=60.0, min_flexion_deg=2.0, rom_deg=58.0,
                              stance_flexion_deg=15.0, estimator="go", quality=1.0, quality_reasons=[]))
            enc = encode_trace(np.arange(100) / 100.0, np.zeros(100), np.array(["go"] * 100), 100.0)
            db.add(KneeAngleTrace(session_id=sess["id"], leg="left", t0_s=enc.t0_s, fs_hz=enc.fs_hz, n=enc.n,
                                  angle_deg=enc.angle_deg, estimator_codes=enc.estimator_codes,
                                  estimator_names=enc.estimator_names))
            db.commit()
    return patient["id"]


def test_delete_patient_removes_all_its_rows_and_nothing_else(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    keep = _fill_patient(api, clin)
    baseline = count_rows(api.engine)
    gone = _fill_patient(api, clin)
    full = count_rows(api.engine)
    for table in ("patients", "sessions", "session_sensors", "batches", "strides", "knee_angle_traces", "tokens"):
        assert full[table] > baseline[table], table
    assert c.delete(f"/v1/patients/{gone}", headers=bearer(clin)).status_code == 204
    assert count_rows(api.engine) == baseline  # every table, including other modules' tables
    assert c.get(f"/v1/patients/{gone}", headers=bearer(clin)).status_code == 404
    assert c.delete(f"/v1/patients/{gone}", headers=bearer(clin)).status_code == 404
    assert c.get(f"/v1/patients/{keep}", headers=bearer(clin)).status_code == 200


def test_patch_patient_changes_only_given_fields(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    _, other = api.clinician("Other")
    p = api.patient(clin, external_id="MRN-1", display_name="P. One", affected_leg="left")
    dev = api.device(clin, p["id"])
    r = c.patch(f"/v1/patients/{p['id']}", json={"affected_leg": "right", "timezone": "America/New_York"},
                headers=bearer(clin))
    assert r.status_code == 200
    assert {k: r.json()[k] for k in ("external_id", "display_name", "affected_leg", "timezone")} == \
        {"external_id": "MRN-1", "display_name": "P. One", "affected_leg": "right", "timezone": "America/New_York"}
    r = c.patch(f"/v1/patients/{p['id']}", json={"display_name": None}, headers=bearer(clin))
    assert r.status_code == 200 and r.json()["display_name"] is None and r.json()["affected_leg"] == "right"
    for bad in ({"timezone": None}, {"timezone": "Nowhere/City"}, {"affected_leg": "x"}, {"clinician_id": "x"}):
        assert c.patch(f"/v1/patients/{p['id']}", json=bad, headers=bearer(clin)).status_code == 422, bad
    assert c.patch(f"/v1/patients/{p['id']}", json={}, headers=bearer(other)).status_code == 404
    assert c.patch(f"/v1/patients/{p['id']}", json={}, headers=bearer(dev)).status_code == 403
    assert c.get(f"/v1/patients/{p['id']}", headers=bearer(clin)).json()["timezone"] == "America/New_York"
