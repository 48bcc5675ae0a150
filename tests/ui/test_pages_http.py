"""The pages over HTTP in process, on SQLite and PostgreSQL: access rules, CSRF, search, every page renders."""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from server.config import Settings
from tests.server.helpers import Api, open_api
from tests.support.seed import add_session

NOW = datetime.now(UTC).replace(microsecond=0)


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def sign_in(api: Api, token: str) -> str:
    """Signs the test client in through the form; returns the page's CSRF token."""
    api.client.cookies.clear()
    form = api.client.get("/ui/login").text
    value = re.search(r'name="form_token" value="([^"]+)"', form).group(1)
    r = api.client.post("/ui/login", data={"token": token, "form_token": value}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/patients", r.text[:300]
    page = api.client.get("/ui/patients")
    return re.search(r'name="csrf" value="([^"]+)"', page.text).group(1)


def seeded(api: Api) -> tuple[str, str, dict, dict]:
    _, clin_a = api.clinician("Dr A")
    _, clin_b = api.clinician("Dr B")
    pa = api.patient(clin_a, external_id="KNEE_100%", affected_leg="left", timezone="Europe/Berlin")
    pb = api.patient(clin_b, external_id="HIP-7")
    with api.client.app.state.sessionmaker() as db:  # type: ignore[attr-defined]
        for k, days_ago in enumerate((20, 13, 6, 1)):
            add_session(db, pa["id"], NOW - timedelta(days=days_ago),
                        {"left": {"n": 30, "peak_swing_flexion_deg": np.full(30, 40.0 + 5 * k)},
                         "right": {"n": 30, "peak_swing_flexion_deg": 60.0}})
        add_session(db, pb["id"], NOW - timedelta(days=2), {"left": {"n": 30}})
        db.commit()
    return clin_a, clin_b, pa, pb


def test_pages_render_and_keep_patients_apart(api: Api) -> None:
    clin_a, clin_b, pa, pb = seeded(api)
    c = api.client
    assert c.get("/ui/patients", follow_redirects=False).headers["location"] == "/ui/login"
    sign_in(api, clin_a)
    page = c.get("/ui/patients")
    assert page.status_code == 200 and "KNEE_100%" in page.text and "HIP-7" not in page.text
    assert "no-store" in page.headers["cache-control"] and "script-src" not in page.headers["content-security-policy"]
    # LIKE wildcards in the search are literal characters
    def listed(q: str) -> str:  # the table of all patients (the attention list above it is not searched)
        return c.get("/ui/patients", params={"q": q}).text.split('id="all-h"', 1)[1]

    assert "KNEE_100%" in listed("_100%") and "KNEE_100%" in listed("knee")
    assert "KNEE_100%" not in listed("E%1") and "KNEE_100%" not in listed("K_E")
    detail = c.get(f"/ui/patients/{pa['id']}")
    assert detail.status_code == 200 and detail.text.count('<svg xmlns="http://www.w3.org/2000/svg"') >= 6
    assert "Peak knee flexion in swing" in detail.text and "per week" in detail.text
    sessions = re.findall(r'href="/ui/sessions/([0-9a-f]{32})"', detail.text)
    assert len(sessions) == 4
    s = c.get(f"/ui/sessions/{sessions[0]}")
    assert s.status_code == 200 and "Strides (60, 60 trustworthy)" in s.text
    assert c.get(f"/ui/sessions/{sessions[0]}", params={"start": "abc"}).status_code == 422
    csv = c.get(f"/ui/patients/{pa['id']}/strides.csv")
    assert csv.status_code == 200 and len(csv.text.splitlines()) == 1 + 4 * 60
    # the other clinician's patient: 404 by URL, for pages and downloads alike
    for url in (f"/ui/patients/{pb['id']}", f"/ui/patients/{pb['id']}/strides.csv",
                f"/ui/patients/{pb['id']}/fhir.json", "/ui/sessions/" + "0" * 32):
        r = c.get(url)
        assert r.status_code == 404 and "text/html" in r.headers["content-type"] and "HIP-7" not in r.text, url
    sign_in(api, clin_b)
    assert c.get(f"/ui/patients/{pa['id']}").status_code == 404
    assert c.get(f"/ui/sessions/{sessions[0]}").status_code == 404
    sign_in(api, api.admin)
    assert c.get(f"/ui/patients/{pa['id']}").status_code == 200


def test_device_token_revocation_and_csrf(api: Api) -> None:
    clin_a, _, pa, _ = seeded(api)
    c = api.client
    device = api.device(clin_a, pa["id"])
    form = c.get("/ui/login").text
    value = re.search(r'name="form_token" value="([^"]+)"', form).group(1)
    r = c.post("/ui/login", data={"token": device, "form_token": value}, follow_redirects=False)
    assert r.status_code == 403 and "device token" in r.text and "gaitmon_ui=" not in r.headers.get("set-cookie", "")
    r = c.post("/ui/login", data={"token": clin_a}, follow_redirects=False)
    assert r.status_code == 403  # no double-submit value
    csrf = sign_in(api, clin_a)
    assert c.post("/ui/logout", data={}, follow_redirects=False).status_code == 403
    assert c.post("/ui/logout", data={"csrf": csrf[:-1] + "x"}, follow_redirects=False).status_code == 403
    cookie = c.cookies.get("gaitmon_ui")
    forged = cookie.rsplit(".", 1)[0] + "." + "0" * 64  # a session cookie whose MAC does not match
    c.cookies.set("gaitmon_ui", forged, path="/ui")
    assert c.get("/ui/patients", follow_redirects=False).status_code == 303
    c.cookies.set("gaitmon_ui", cookie, path="/ui")
    assert c.get("/ui/patients").status_code == 200
    r = c.post("/ui/logout", data={"csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/ui/login"
    # a revoked token ends its page sessions at once
    sign_in(api, clin_a)
    assert c.get("/ui/patients").status_code == 200
    token_id = c.get("/v1/me", headers={"Authorization": f"Bearer {clin_a}"}).json()["token_id"]
    assert c.delete(f"/v1/tokens/{token_id}", headers={"Authorization": f"Bearer {api.admin}"}).status_code == 204
    assert c.get("/ui/patients", follow_redirects=False).status_code == 303


def test_cached_trends_follow_new_sessions(api: Api) -> None:
    from server.patients.models import Patient
    from server.ui import data

    _, _, pa, _ = seeded(api)
    with api.client.app.state.sessionmaker() as db:  # type: ignore[attr-defined]
        patient = db.get(Patient, pa["id"])
        before = data.trends(db, patient, "peak_swing_flexion_deg", "left", "day")
        assert data.trends(db, patient, "peak_swing_flexion_deg", "left", "day") is before  # served from memory
        add_session(db, pa["id"], NOW - timedelta(hours=1), {"left": {"n": 30, "peak_swing_flexion_deg": 80.0}})
        db.commit()
        after = data.trends(db, patient, "peak_swing_flexion_deg", "left", "day")
        assert after["buckets"][-1]["mean"] != before["buckets"][-1]["mean"] or \
            len(after["buckets"]) == len(before["buckets"]) + 1
        assert after["trend"]["n"] == before["trend"]["n"] + 1


def test_crafted_cookies_of_device_tokens_and_expired_sessions_get_no_page(api: Api) -> None:
    import time

    from server.ui import signin

    clin_a, _, pa, _ = seeded(api)
    device = api.device(clin_a, pa["id"])
    c = api.client

    def cookie(token: str, issued: int) -> str:
        nonce = "n0nce"
        return f"{token}.{nonce}.{issued}.{signin._mac(token, f'session|{nonce}|{issued}')}"

    c.cookies.clear()
    # whoever holds a device token can compute a well-formed cookie for it: still no pages
    c.cookies.set(signin.COOKIE, cookie(device, int(time.time())), path="/ui")
    r = c.get("/ui/patients", follow_redirects=False)
    assert r.status_code == 403 and "device token" in r.text
    assert c.get(f"/ui/patients/{pa['id']}", follow_redirects=False).status_code == 403
    c.cookies.set(signin.COOKIE, cookie(clin_a, int(time.time()) - signin.MAX_AGE_S - 60), path="/ui")
    assert c.get("/ui/patients", follow_redirects=False).headers["location"] == "/ui/login"
    c.cookies.set(signin.COOKIE, cookie(clin_a, int(time.time())), path="/ui")
    assert c.get("/ui/patients", follow_redirects=False).status_code == 200


def test_pages_of_a_new_patient_and_an_unfinished_session(api: Api) -> None:
    _, clin = api.clinician()
    p = api.patient(clin, external_id="NEW-1")
    sess = api.session(clin, p["id"])  # receiving, nothing uploaded
    sign_in(api, clin)
    page = api.client.get(f"/ui/patients/{p['id']}")
    assert page.status_code == 200 and "No processed session with strides yet" in page.text
    assert "Receiving data from the phone" in page.text
    s = api.client.get(f"/ui/sessions/{sess['id']}")
    assert s.status_code == 200 and "Results\nappear here once the session is processed" in s.text
    r = api.client.get(f"/ui/sessions/{sess['id']}/compare")
    assert r.status_code == 409 and "still receiving" in r.text
    listing = api.client.get("/ui/patients").text
    assert "NEW-1" in listing and "No session since enrolment" not in listing  # enrolled just now


def test_calibration_entry_records_through_the_api_rule(api: Api) -> None:
    """The patient page's calibration form stores what the API stores (noon of the local day), needs the page's CSRF
    token, refuses impossible values, and stays inside the clinician's own patients."""
    clin_a, clin_b, pa, pb = seeded(api)
    c = api.client
    csrf = sign_in(api, clin_a)
    form = {"csrf": csrf, "leg": "left", "standing_knee_deg": "11.5", "measured_on": "2026-11-02",
            "method": "goniometer"}
    r = c.post(f"/ui/patients/{pa['id']}/calibrations", data=form, follow_redirects=False)
    # the four seeded sessions started after the measurement: a reprocess would change them
    assert r.status_code == 303 and "calibrated=4" in r.headers["location"]
    items = c.get(f"/v1/patients/{pa['id']}/calibrations", headers={"Authorization": f"Bearer {clin_a}"}
                  ).json()["items"]
    assert [(i["leg"], i["standing_knee_deg"], i["method"]) for i in items] == [("left", 11.5, "goniometer")]
    assert items[0]["measured_at"].startswith("2026-11-02T11:00:00")  # noon in Europe/Berlin, stored in UTC
    page = c.get(r.headers["location"])
    assert "11.5\u00b0" in page.text and "Calibration recorded. 4 processed" in page.text
    assert c.post(f"/ui/patients/{pa['id']}/calibrations", data={**form, "csrf": "forged"}).status_code == 403
    assert c.post(f"/ui/patients/{pa['id']}/calibrations", data={**form, "standing_knee_deg": "95"}).status_code == 422
    assert c.post(f"/ui/patients/{pb['id']}/calibrations", data=form).status_code == 404
    items = c.get(f"/v1/patients/{pa['id']}/calibrations", headers={"Authorization": f"Bearer {clin_a}"}
                  ).json()["items"]
    assert len(items) == 1


def test_addresses_no_page_route_answers_get_pages_and_the_api_keeps_problems(api: Api) -> None:
    c = api.client
    c.cookies.clear()

    def is_page(r, status: int, title: str) -> None:  # noqa: ANN001
        assert r.status_code == status and r.headers["content-type"].startswith("text/html"), r.text[:200]
        assert f"<h1>{title}</h1>" in r.text and "Traceback" not in r.text
        assert r.headers["content-security-policy"].startswith("default-src 'none'")

    is_page(c.get("/ui/no-such-page"), 404, "Not found")
    is_page(c.get("/ui/static/no-such.css"), 404, "Not found")
    # text no database can store, in the path or the query, refused before any route (and any query) runs
    is_page(c.get("/ui/patients/abc%00"), 422, "Invalid address")
    is_page(c.get("/ui/patients?cursor=%00"), 422, "Invalid address")
    r = c.delete("/ui/patients")
    is_page(r, 405, "Method Not Allowed")
    assert "GET" in r.headers["allow"]
    # the API's addresses answer as before: problem details
    for r, status in ((c.get("/v1/no-such-route"), 404), (c.get("/v1/sessions/a%00b"), 422),
                      (c.get("/uix%00"), 422)):
        assert r.status_code == status and r.headers["content-type"] == "application/problem+json", r.text[:200]
