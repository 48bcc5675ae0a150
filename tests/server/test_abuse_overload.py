"""Transient trouble is 503 + Retry-After, never 500 nor a wait without end: an unreachable database, a pool with
no free connection, more requests in flight than the process takes."""

from __future__ import annotations

import gc
import time

from fastapi.testclient import TestClient

from server.app import create_app
from server.config import Settings
from tests.server.helpers import bearer, open_api


def _assert_503(r) -> None:  # noqa: ANN001
    assert r.status_code == 503, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    assert int(r.headers["retry-after"]) >= 1


def test_an_unreachable_database_is_503_with_retry_after(tmp_path) -> None:  # noqa: ANN001
    s = Settings(database_url="postgresql+psycopg://postgres@127.0.0.1:1/nothing", data_dir=tmp_path,
                 job_runner="manual")
    with TestClient(create_app(s), raise_server_exceptions=False) as c:
        t0 = time.perf_counter()
        _assert_503(c.get("/v1/me", headers=bearer("gm_whatever")))
        assert time.perf_counter() - t0 < 10
        assert c.get("/healthz").status_code == 503


def test_no_free_pooled_connection_is_503_within_the_pool_timeout(settings: Settings) -> None:
    tight = settings.model_copy(update={"db_pool_size": 1, "db_max_overflow": 0, "db_pool_timeout_s": 0.2})
    with open_api(tight) as api:
        with api.engine.connect():  # the only connection of the pool is taken
            t0 = time.perf_counter()
            _assert_503(api.client.get("/v1/me", headers=bearer(api.admin)))
            assert time.perf_counter() - t0 < 5
        assert api.client.get("/v1/me", headers=bearer(api.admin)).status_code == 200


def test_requests_beyond_the_in_flight_limit_are_refused_but_health_checks_are_not(settings: Settings) -> None:
    with open_api(settings.model_copy(update={"max_in_flight": 0})) as api:
        _assert_503(api.client.get("/v1/me", headers=bearer(api.admin)))
        assert api.client.get("/healthz").status_code == 200


def test_the_start_up_objects_are_out_of_the_collectors_sight(settings: Settings) -> None:
    # A full collection then scans only what requests allocate, not every imported module (0.1-0.3 s pauses).
    with open_api(settings):
        assert gc.get_freeze_count() > 100_000
