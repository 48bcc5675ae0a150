"""The abuse catalogue: hostile or broken input is answered 4xx (never 5xx) and leaves the session unchanged."""

from __future__ import annotations

import gzip
import json
from collections.abc import Iterator
from typing import Any

import pytest

from server.config import Settings
from tests.server.helpers import SENSORS_LEFT, Api, batch_body, bearer, count_rows, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def _state(api: Api, dev: str, sid: str) -> tuple[dict[str, Any], dict[str, int]]:
    s = api.client.get(f"/v1/sessions/{sid}", headers=bearer(dev)).json()
    return {k: s[k] for k in ("status", "received", "completed_at")}, count_rows(api.engine)


def _assert_4xx_problem(r, status: int) -> None:  # noqa: ANN001
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["status"] == status


def _post_raw(api: Api, dev: str, sid: str, data: bytes, **headers: str):  # noqa: ANN202
    return api.client.post(f"/v1/sessions/{sid}/batches", content=data,
                           headers={**bearer(dev), "Content-Type": "application/json", **headers})


@pytest.mark.parametrize("where", ["sensor_id", "client_session_id", "patient_id", "path", "query", "external_id",
                                   "display_name", "clinician_name", "cursor"])
@pytest.mark.parametrize("char", ["\x00", "\ud800"])
def test_nul_and_lone_surrogates_are_refused_with_422_everywhere(api: Api, where: str, char: str) -> None:
    clin, dev, sess = api.setup_device_session()
    sid = sess["id"]
    before = _state(api, dev, sid)
    bad = f"x{char}y"
    # json.dumps escapes a lone surrogate as \ud800, which is valid JSON text
    c = api.client
    if where == "sensor_id":
        r = _post_raw(api, dev, sid, json.dumps({**batch_body("L-shank", 0), "sensor_id": bad}).encode())
    elif where in ("client_session_id", "patient_id"):
        body = {"patient_id": sess["patient_id"], "client_session_id": "c2", "started_at": "2026-11-21T09:30:00Z",
                "sensors": SENSORS_LEFT, where: bad}
        r = c.post("/v1/sessions", content=json.dumps(body).encode(),
                   headers={**bearer(dev), "Content-Type": "application/json"})
    elif where == "path":
        r = c.get(f"/v1/sessions/{sid}%00", headers=bearer(dev)) if char == "\x00" else \
            c.get(f"/v1/sessions/{sid}%ED%A0%80", headers=bearer(dev))
        if char != "\x00":
            # Invalid UTF-8 in a path decodes to U+FFFD, storable text: an ordinary 404.
            assert r.status_code == 404, r.text
            return
    elif where == "query":
        r = c.get("/v1/patients?cursor=a%00b", headers=bearer(clin))
        if char != "\x00":
            return
    elif where in ("external_id", "display_name"):
        r = c.post("/v1/patients", content=json.dumps({where: bad}).encode(),
                   headers={**bearer(clin), "Content-Type": "application/json"})
    elif where == "clinician_name":
        r = c.post("/v1/clinicians", content=json.dumps({"name": bad}).encode(),
                   headers={**bearer(api.admin), "Content-Type": "application/json"})
    else:
        r = c.get("/v1/patients", params={"cursor": bad}, headers=bearer(clin)) if char == "\x00" else None
        if r is None:
            return
    _assert_4xx_problem(r, 422)
    assert _state(api, dev, sid) == before


@pytest.mark.parametrize("started_at", ["9999-12-31T23:59:59-14:00", "0001-01-01T00:00:00+14:00",
                                        "1999-12-31T23:59:59Z", "2999-01-01T00:00:00Z", 0, 1700000000,
                                        "2026-11-21T09:30:00"])
def test_started_at_outside_2000_to_tomorrow_or_not_an_aware_string_is_422(api: Api, started_at: Any) -> None:
    _, dev, sess = api.setup_device_session()
    before = count_rows(api.engine)
    body = {"patient_id": sess["patient_id"], "client_session_id": "late", "started_at": started_at,
            "sensors": SENSORS_LEFT}
    _assert_4xx_problem(api.client.post("/v1/sessions", json=body, headers=bearer(dev)), 422)
    assert count_rows(api.engine) == before


def test_sessions_at_the_started_at_limits_keep_trends_symmetry_and_fhir_answering(api: Api) -> None:
    from datetime import UTC, datetime, timedelta

    clin, dev, sess = api.setup_device_session()
    pid = sess["patient_id"]
    for k, when in enumerate(["2000-01-01T00:00:00+00:00",
                              (datetime.now(UTC) + timedelta(hours=23)).isoformat(timespec="seconds")]):
        body = {"patient_id": pid, "client_session_id": f"edge-{k}", "started_at": when, "sensors": SENSORS_LEFT}
        assert api.client.post("/v1/sessions", json=body, headers=bearer(dev)).status_code == 201
    for path in ("trends", "symmetry", "fhir", "strides.csv", "sessions"):
        r = api.client.get(f"/v1/patients/{pid}/{path}", headers=bearer(clin))
        assert r.status_code < 500, (path, r.status_code, r.text[:300])


@pytest.mark.parametrize("patch", [{"seq": "1"}, {"seq": True}, {"seq": 1.0}, {"t0_ms": True}, {"t0_ms": "0"},
                                   {"gyro": [[True, 0, 0]] * 50}, {"gyro": [["1", 0, 0]] * 50},
                                   {"gyro": [[3.5e38, 0, 0]] * 50}, {"acc": [[0, -1e39, 0]] * 50}])
def test_lax_types_and_values_beyond_float32_are_422(api: Api, patch: dict[str, Any]) -> None:
    _, dev, sess = api.setup_device_session()
    before = _state(api, dev, sess["id"])
    body = {**batch_body("L-shank", 1), **patch}
    _assert_4xx_problem(api.upload(dev, sess["id"], body), 422)
    assert _state(api, dev, sess["id"]) == before


@pytest.mark.parametrize("content_type", [None, "text/plain", "application/x-www-form-urlencoded"])
def test_json_bodies_need_a_json_content_type(api: Api, content_type: str | None) -> None:
    _, dev, sess = api.setup_device_session()
    before = _state(api, dev, sess["id"])
    headers = bearer(dev) | ({"Content-Type": content_type} if content_type else {})
    data = json.dumps(batch_body("L-shank", 0)).encode()
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=data, headers=headers)
    _assert_4xx_problem(r, 415)
    assert _state(api, dev, sess["id"]) == before
    # with the header the same bytes are stored
    r = api.client.post(f"/v1/sessions/{sess['id']}/batches", content=data,
                        headers=bearer(dev) | {"Content-Type": "application/json; charset=utf-8"})
    assert r.status_code == 201, r.text


def _million_rows() -> bytes:
    rows = b"[1,2,3]," * 999_999 + b"[1,2,3]"
    return b'{"sensor_id":"L-shank","seq":0,"t0_ms":0,"gyro":[' + rows + b'],"acc":[' + b"[1,2,3]" + b"]}"


def _assert_refused_from_bytes(api: Api, data: bytes, gzipped: bool, word: str) -> None:
    """``data`` (under the body limit) posted as a batch is 422 naming ``word``, within 3 s, session unchanged."""
    import time

    _, dev, sess = api.setup_device_session()
    before = _state(api, dev, sess["id"])
    assert len(data) < api.settings.max_body_bytes
    extra = {"Content-Encoding": "gzip"} if gzipped else {}
    t0 = time.perf_counter()
    r = _post_raw(api, dev, sess["id"], gzip.compress(data) if gzipped else data, **extra)
    elapsed = time.perf_counter() - t0
    _assert_4xx_problem(r, 422)
    assert word in r.json()["detail"]
    assert elapsed < 3.0, elapsed
    assert _state(api, dev, sess["id"]) == before


@pytest.mark.parametrize("gzipped", [False, True])
def test_a_million_row_body_is_refused_from_its_bytes(api: Api, gzipped: bool) -> None:
    # Counting brackets on 8 MB is milliseconds; building a million Python lists took seconds.
    _assert_refused_from_bytes(api, _million_rows(), gzipped, "samples")


def test_gzip_of_many_empty_members_is_refused(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    before = _state(api, dev, sess["id"])
    empty = gzip.compress(b"")
    data = empty * 10_000 + gzip.compress(json.dumps(batch_body("L-shank", 0)).encode())
    r = _post_raw(api, dev, sess["id"], data, **{"Content-Encoding": "gzip"})
    _assert_4xx_problem(r, 400)
    assert "gzip members" in r.json()["detail"]
    assert _state(api, dev, sess["id"]) == before


def _span_attack_session(api: Api, dev: str, pid: str) -> str:
    sensors = [{**s, "sample_rate_hz": 2000} for s in SENSORS_LEFT]
    sid = api.session(dev, pid, client_session_id="span", sensors=sensors)["id"]
    for sensor in ("L-thigh", "L-shank"):
        for seq, t0 in enumerate((0.0, 2e6)):
            body = {"sensor_id": sensor, "seq": seq, "t0_ms": t0, "gyro": [[1.0, 2.0, 3.0]] * 3,
                    "acc": [[0.0, 0.0, 9.81]] * 3, "timestamps_ms": [t0, t0 + 0.5, t0 + 1.0]}
            assert api.upload(dev, sid, body).status_code == 201
    return sid


def test_twelve_samples_spanning_2000_s_at_2000_hz_are_refused_at_complete(api: Api) -> None:
    _, dev, sess = api.setup_device_session()
    sid = _span_attack_session(api, dev, sess["patient_id"])
    before = _state(api, dev, sid)
    r = api.client.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev))
    _assert_4xx_problem(r, 422)
    assert "L-shank" in r.json()["detail"] or "L-thigh" in r.json()["detail"]
    assert _state(api, dev, sid) == before
    assert before[0]["status"] == "receiving"


def test_a_queued_span_attack_fails_processing_before_decoding_any_sample(api: Api) -> None:
    import resource

    from sqlalchemy import update

    from server.processing.jobs import process_one
    from server.sessions.models import Session

    _, dev, sess = api.setup_device_session()
    sid = _span_attack_session(api, dev, sess["patient_id"])
    sm = api.client.app.state.sessionmaker  # type: ignore[attr-defined]
    with sm() as db:  # as if queued before the /complete check existed
        db.execute(update(Session).where(Session.id == sid).values(status="queued"))
        db.commit()
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    assert process_one(sm, sid) == "failed"
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before) / 1024
    s = api.client.get(f"/v1/sessions/{sid}", headers=bearer(dev)).json()
    assert s["status"] == "failed"
    assert "grid points" in s["error"]
    assert grown_mb < 50, grown_mb


def test_a_session_longer_than_the_maximum_duration_is_refused(settings: Settings) -> None:
    with open_api(settings.model_copy(update={"max_session_s": 60.0})) as api:
        _, dev, sess = api.setup_device_session()
        for sensor in ("L-thigh", "L-shank"):
            for seq in range(3):
                # 50-sample batches 40 s apart: the sensor spans 80.5 s, over the 60 s maximum
                assert api.upload(dev, sess["id"], batch_body(sensor, seq, t0_ms=seq * 40_000.0)).status_code == 201
        r = api.client.post(f"/v1/sessions/{sess['id']}/complete", headers=bearer(dev))
        _assert_4xx_problem(r, 422)
        assert "maximum session duration" in r.json()["detail"]


@pytest.mark.parametrize("external_id", ["患者-42", "evil\r\nSet-Cookie: x=1", 'quote"and\\back', "é-latin1"])
def test_strides_csv_filenames_follow_rfc_6266_and_5987(api: Api, external_id: str) -> None:
    from urllib.parse import quote

    clin = api.clinician()[1]
    r = api.client.post("/v1/patients", json={"external_id": external_id}, headers=bearer(clin))
    assert r.status_code == 201, r.text
    pid = r.json()["id"]
    r = api.client.get(f"/v1/patients/{pid}/strides.csv", headers=bearer(clin))
    assert r.status_code == 200, r.text
    cd = r.headers["content-disposition"]
    assert "\r" not in cd and "\n" not in cd
    cd.encode("latin-1")
    assert f"filename*=UTF-8''{quote(f'strides-{external_id}.csv', safe='')}" in cd
    assert cd.startswith('attachment; filename="strides-')


@pytest.mark.parametrize("element", [b"{}", b"1"])
def test_a_flood_of_tiny_values_is_refused_from_its_bytes(api: Api, element: bytes) -> None:
    """Two million empty objects or bare numbers gzip to a few kB; validating them built one error object each
    (seconds and gigabytes). The separators are counted on the bytes first."""
    data = b'{"sensor_id":"L-shank","seq":1,"t0_ms":0,"gyro":[' + b",".join([element] * 2_000_000) + b'],"acc":[]}'
    _assert_refused_from_bytes(api, data, True, "values")


def test_a_large_body_to_a_small_endpoint_is_413_before_validation(api: Api) -> None:
    import time

    _, clin = api.clinician()
    data = ("{" + ",".join(f'"k{i}":1' for i in range(700_000)) + "}").encode()
    t0 = time.perf_counter()
    r = api.client.post("/v1/patients", content=data, headers=bearer(clin) | {"Content-Type": "application/json"})
    _assert_4xx_problem(r, 413)
    assert time.perf_counter() - t0 < 3.0


@pytest.mark.parametrize("tz", ["Europe", "America", "Etc"])
def test_a_time_zone_folder_is_no_time_zone(api: Api, tz: str) -> None:
    _, clin = api.clinician()
    r = api.client.post("/v1/patients", json={"timezone": tz}, headers=bearer(clin))
    _assert_4xx_problem(r, 422)


@pytest.mark.parametrize("query", ["to=9999-12-31", "from=0001-01-01", "to=9999-12-31T23:00:00-05:00"])
@pytest.mark.parametrize("path", ["trends", "symmetry", "fhir", "strides.csv"])
def test_dates_at_the_calendar_ends_are_422_not_500(api: Api, query: str, path: str) -> None:
    _, clin = api.clinician()
    pid = api.patient(clin, timezone="Asia/Tokyo")["id"]
    r = api.client.get(f"/v1/patients/{pid}/{path}?{query}", headers=bearer(clin))
    assert r.status_code == 422, (path, query, r.status_code, r.text[:300])


def test_client_text_cannot_become_a_spreadsheet_formula() -> None:
    from server.trends.exports import _text_cell

    assert _text_cell('=HYPERLINK("http://evil.example/","open")').startswith("'=")
    assert _text_cell("@SUM(A1)") == "'@SUM(A1)" and _text_cell("-1+2") == "'-1+2"
    assert _text_cell("visit-3") == "visit-3" and _text_cell(None) == ""


@pytest.mark.parametrize("value", [True, "3", float("nan")])
def test_prescribed_sessions_per_week_is_a_strict_number(api: Api, value: Any) -> None:
    _, clin = api.clinician()
    pid = api.patient(clin)["id"]
    body = json.dumps({"prescribed_sessions_per_week": value}).encode()  # NaN as the literal Python's json writes
    for method, url in (("POST", "/v1/patients"), ("PATCH", f"/v1/patients/{pid}")):
        r = api.client.request(method, url, content=body, headers=bearer(clin) | {"Content-Type": "application/json"})
        _assert_4xx_problem(r, 422)
    assert api.client.get(f"/v1/patients/{pid}", headers=bearer(clin)).json()["prescribed_sessions_per_week"] is None
