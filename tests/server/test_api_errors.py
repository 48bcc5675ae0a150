"""Every error is an RFC 9457 problem document; health check; OpenAPI docs."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.config import Settings
from tests.server.helpers import Api, bearer, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def _assert_problem(r, status: int) -> dict:  # noqa: ANN001
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["status"] == status
    assert isinstance(body["type"], str) and body["type"]
    assert isinstance(body["title"], str) and body["title"]
    assert isinstance(body["detail"], str) and body["detail"]
    return body


def test_unknown_route_and_wrong_method(api: Api) -> None:
    body = _assert_problem(api.client.get("/v1/nothing-here", headers=bearer(api.admin)), 404)
    assert body["instance"] == "/v1/nothing-here"
    _assert_problem(api.client.put("/v1/patients", headers=bearer(api.admin)), 405)
    _assert_problem(api.client.get("/v1/sessions/doesnotexist", headers=bearer(api.admin)), 404)


def test_validation_error_lists_fields(api: Api) -> None:
    _, clin = api.clinician()
    body = {"patient_id": "x", "client_session_id": "", "started_at": "yesterday", "activity": "dancing",
            "sensors": []}
    problem = _assert_problem(api.client.post("/v1/sessions", json=body, headers=bearer(clin)), 422)
    fields = {e["field"] for e in problem["errors"]}
    assert {"client_session_id", "started_at", "activity", "sensors"} <= fields
    assert all(e["message"] for e in problem["errors"])


def test_internal_error_is_a_problem_without_traceback(settings: Settings) -> None:
    app = create_app(settings)

    @app.get("/boom")
    def boom() -> None:
        raise RuntimeError("secret internals at /etc/passwd")

    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.get("/boom")
    body = _assert_problem(r, 500)
    assert "secret" not in r.text and "Traceback" not in r.text and "RuntimeError" not in r.text
    assert body["title"] == "Internal Server Error"


def test_healthz_ok_and_unavailable(api: Api, tmp_path: Path) -> None:
    r = api.client.get("/healthz")
    assert r.status_code == 200 and r.json()["status"] == "ok"
    broken = Settings(database_url=f"sqlite:///{tmp_path}/missing-dir/x.sqlite", data_dir=tmp_path,
                      job_runner="manual")
    with TestClient(create_app(broken), raise_server_exceptions=False) as client:
        _assert_problem(client.get("/healthz"), 503)


def test_openapi_and_docs(api: Api) -> None:
    spec = api.client.get("/openapi.json").json()
    for path in ("/v1/sessions/{session_id}/batches", "/v1/patients", "/v1/clinicians", "/v1/tokens/{token_id}",
                 "/v1/sessions/{session_id}/knee-angle", "/v1/me", "/healthz"):
        assert path in spec["paths"], path
    tags = {t for p in spec["paths"].values() for op in p.values() for t in op.get("tags", [])}
    assert {"patients", "sessions and upload", "results", "health"} <= tags
    batch = spec["paths"]["/v1/sessions/{session_id}/batches"]["post"]
    ref = batch["requestBody"]["content"]["application/json"]["schema"]["$ref"]
    assert {"sensor_id", "seq", "t0_ms", "gyro", "acc", "timestamps_ms"} <= \
        set(spec["components"]["schemas"][ref.rsplit("/", 1)[-1]]["properties"])
    assert api.client.get("/docs").status_code == 200


def test_large_responses_are_gzipped_when_accepted(api: Api) -> None:
    r = api.client.get("/openapi.json", headers={"Accept-Encoding": "gzip"})
    assert r.headers.get("content-encoding") == "gzip" and "paths" in r.json()
    r = api.client.get("/openapi.json", headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in r.headers and "paths" in r.json()


def test_upload_answers_are_never_compressed_and_carry_no_vary(api: Api) -> None:
    """Uploads bypass the response GZip middleware (their answers are always below its minimum size): a 201, a 200
    replay and a 422 problem go out plain, without the Vary header a compressed answer would carry."""
    from tests.server.helpers import batch_body

    _, dev, sess = api.setup_device_session()
    url = f"/v1/sessions/{sess['id']}/batches"
    statuses = []
    for body in (batch_body("L-thigh", 0, n=20), batch_body("L-thigh", 0, n=20), {"sensor_id": "L-thigh"}):
        r = api.client.post(url, json=body, headers={**bearer(dev), "Accept-Encoding": "gzip"})
        statuses.append(r.status_code)
        assert "content-encoding" not in r.headers and "vary" not in r.headers and len(r.content) < 1024
        assert r.json()
    assert statuses == [201, 200, 422]
