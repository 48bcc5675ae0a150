"""Auth matrix: 401 without a valid token, 403 for a role that may never act, 404 across patients/clinicians."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy import text

from server.config import Settings
from tests.server.helpers import Api, batch_body, bearer, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def test_missing_malformed_and_unknown_tokens_get_401_problem(api: Api) -> None:
    c = api.client
    for headers in ({}, {"Authorization": "Basic abc"}, {"Authorization": "Bearer "},
                    bearer("gm_not-a-real-token")):
        r = c.get("/v1/patients", headers=headers)
        assert r.status_code == 401, headers
        assert r.headers["content-type"].startswith("application/problem+json")
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert r.json()["status"] == 401


def test_me_reports_role_and_binding(api: Api) -> None:
    clin_id, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    me = api.client.get("/v1/me", headers=bearer(dev)).json()
    assert me["role"] == "device" and me["patient_id"] == patient["id"] and me["clinician_id"] is None
    me = api.client.get("/v1/me", headers=bearer(clin)).json()
    assert me["role"] == "clinician" and me["clinician_id"] == clin_id
    assert api.client.get("/v1/me", headers=bearer(api.admin)).json()["role"] == "admin"


def test_role_matrix_403(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    sess = api.session(dev, patient["id"])
    # Clinicians may not manage clinicians; devices may not manage patients, tokens or reprocess.
    assert c.post("/v1/clinicians", json={"name": "x"}, headers=bearer(clin)).status_code == 403
    assert c.post("/v1/clinicians", json={"name": "x"}, headers=bearer(dev)).status_code == 403
    assert c.post("/v1/patients", json={}, headers=bearer(dev)).status_code == 403
    assert c.get("/v1/patients", headers=bearer(dev)).status_code == 403
    assert c.delete(f"/v1/patients/{patient['id']}", headers=bearer(dev)).status_code == 403
    assert c.post(f"/v1/patients/{patient['id']}/device-tokens", headers=bearer(dev)).status_code == 403
    assert c.post(f"/v1/sessions/{sess['id']}/reprocess", headers=bearer(dev)).status_code == 403
    r = c.delete(f"/v1/tokens/{api.client.get('/v1/me', headers=bearer(dev)).json()['token_id']}",
                 headers=bearer(dev))
    assert r.status_code == 403
    assert r.headers["content-type"].startswith("application/problem+json")


def test_cross_patient_and_cross_clinician_get_404(api: Api) -> None:
    c = api.client
    _, clin_a = api.clinician("A")
    _, clin_b = api.clinician("B")
    pa = api.patient(clin_a)
    pa2 = api.patient(clin_a)
    pb = api.patient(clin_b)
    dev_a = api.device(clin_a, pa["id"])
    sess_a = api.session(dev_a, pa["id"])
    # Clinician B sees nothing of A's patient or session.
    assert c.get(f"/v1/patients/{pa['id']}", headers=bearer(clin_b)).status_code == 404
    assert c.delete(f"/v1/patients/{pa['id']}", headers=bearer(clin_b)).status_code == 404
    assert c.post(f"/v1/patients/{pa['id']}/device-tokens", headers=bearer(clin_b)).status_code == 404
    assert c.get(f"/v1/sessions/{sess_a['id']}", headers=bearer(clin_b)).status_code == 404
    assert c.get(f"/v1/sessions/{sess_a['id']}/strides", headers=bearer(clin_b)).status_code == 404
    assert api.upload(clin_b, sess_a["id"], batch_body("L-thigh", 0)).status_code == 404
    assert [p["id"] for p in c.get("/v1/patients", headers=bearer(clin_b)).json()["items"]] == [pb["id"]]
    # A device token is bound to its patient: another patient of the same clinician is unknown to it.
    body = {"patient_id": pa2["id"], "client_session_id": "x", "started_at": "2026-11-21T09:30:00+00:00",
            "sensors": [{"sensor_id": "s", "leg": "left", "segment": "thigh", "sample_rate_hz": 100}]}
    assert c.post("/v1/sessions", json=body, headers=bearer(dev_a)).status_code == 404
    assert c.get(f"/v1/patients/{pa2['id']}", headers=bearer(dev_a)).status_code == 404
    assert c.get(f"/v1/patients/{pa['id']}", headers=bearer(dev_a)).status_code == 200
    dev_b = api.device(clin_b, pb["id"])
    assert c.get(f"/v1/sessions/{sess_a['id']}", headers=bearer(dev_b)).status_code == 404
    assert api.upload(dev_b, sess_a["id"], batch_body("L-thigh", 0)).status_code == 404
    # The admin sees everything.
    assert c.get(f"/v1/sessions/{sess_a['id']}", headers=bearer(api.admin)).status_code == 200
    assert {p["id"] for p in c.get("/v1/patients", headers=bearer(api.admin)).json()["items"]} == \
        {pa["id"], pa2["id"], pb["id"]}


def test_revoked_tokens_get_401_and_revocation_rights(api: Api) -> None:
    c = api.client
    _, clin_a = api.clinician("A")
    _, clin_b = api.clinician("B")
    pa = api.patient(clin_a)
    dev = api.device(clin_a, pa["id"])
    dev_id = c.get("/v1/me", headers=bearer(dev)).json()["token_id"]
    clin_a_id = c.get("/v1/me", headers=bearer(clin_a)).json()["token_id"]
    # Another clinician may not revoke it (and may not learn it exists).
    assert c.delete(f"/v1/tokens/{dev_id}", headers=bearer(clin_b)).status_code == 404
    assert c.delete(f"/v1/tokens/{clin_a_id}", headers=bearer(clin_b)).status_code == 404
    assert c.get("/v1/me", headers=bearer(dev)).status_code == 200
    # The owning clinician revokes the device token; revoking twice is still 204.
    assert c.delete(f"/v1/tokens/{dev_id}", headers=bearer(clin_a)).status_code == 204
    assert c.delete(f"/v1/tokens/{dev_id}", headers=bearer(clin_a)).status_code == 204
    assert c.get("/v1/me", headers=bearer(dev)).status_code == 401
    listed = c.get(f"/v1/patients/{pa['id']}/device-tokens", headers=bearer(clin_a)).json()
    assert [t["id"] for t in listed] == [dev_id] and listed[0]["revoked_at"] is not None
    # The admin revokes a clinician's token.
    assert c.delete(f"/v1/tokens/{clin_a_id}", headers=bearer(api.admin)).status_code == 204
    assert c.get("/v1/patients", headers=bearer(clin_a)).status_code == 401
    assert c.delete("/v1/tokens/doesnotexist", headers=bearer(api.admin)).status_code == 404


def test_clinician_creation_returns_token_once_and_only_hash_is_stored(api: Api) -> None:
    r = api.client.post("/v1/clinicians", json={"name": "Dr. Who", "email": "who@example.org"},
                        headers=bearer(api.admin))
    assert r.status_code == 201
    body = r.json()
    assert set(body) >= {"id", "name", "token", "token_id"}
    assert api.client.get("/v1/me", headers=bearer(body["token"])).json()["token_id"] == body["token_id"]
    with api.engine.connect() as conn:
        stored = conn.execute(text("select token_hash from tokens where id = :i"), {"i": body["token_id"]}).scalar()
    assert stored != body["token"] and len(stored) == 64
    assert body["token"] not in str(api.client.get("/v1/clinicians", headers=bearer(api.admin)).json())
