"""gaitmon.client against scripted transports: retries, back-off, Retry-After, idempotency rules, gzip, errors."""

from __future__ import annotations

import asyncio
import gzip
import json
import sys
from collections.abc import Callable

import httpx
import pytest

from gaitmon.client import ApiError, AsyncClient, Client, RetryPolicy, Strides

BATCH = {"sensor_id": "L-shank", "seq": 0, "t0_ms": 0.0, "gyro": [[0.0, 1.0, 2.0]], "acc": [[0.0, 0.0, 9.8]]}
BATCH_OK = {"sensor_id": "L-shank", "seq": 0, "samples": 1, "duplicate": False}
PATIENT = {"id": "p1", "timezone": "UTC", "created_at": "2026-11-20T10:00:00Z"}
PROBLEM = {"type": "urn:gaitmon:problem:rate-limited", "title": "Too Many Requests", "status": 429,
           "detail": "Too many requests; retry after 2 s"}


def scripted(answers: list[Callable[[httpx.Request], httpx.Response] | httpx.Response]
             ) -> tuple[httpx.MockTransport, list[httpx.Request]]:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        answer = answers.pop(0)
        return answer(request) if callable(answer) else answer

    return httpx.MockTransport(handler), seen


def fail(exc_type: type[httpx.TransportError]) -> Callable[[httpx.Request], httpx.Response]:
    def raise_(request: httpx.Request) -> httpx.Response:
        raise exc_type("simulated", request=request)
    return raise_


@pytest.fixture
def sleeps(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    slept: list[float] = []
    monkeypatch.setattr("gaitmon.client.sync.time.sleep", slept.append)
    return slept


def test_429_waits_as_long_as_retry_after_says(sleeps: list[float]) -> None:
    transport, seen = scripted([httpx.Response(429, json=PROBLEM, headers={"Retry-After": "2"}),
                                httpx.Response(201, json=BATCH_OK)])
    with Client("http://t", "tok", transport=transport) as c:
        assert c.upload_batch("s1", BATCH).samples == 1
    assert len(seen) == 2 and len(sleeps) == 1
    assert 2.0 <= sleeps[0] <= 2.3  # the server's delay plus a little jitter


def test_503_backs_off_exponentially_with_jitter_then_gives_up(sleeps: list[float]) -> None:
    policy = RetryPolicy(max_attempts=5, base_delay_s=1.0, max_delay_s=5.0)
    transport, seen = scripted([httpx.Response(503, json={"title": "Service Unavailable", "status": 503,
                                                          "detail": "database away"})] * 5)
    with Client("http://t", "tok", transport=transport, retry=policy, seed=3) as c, pytest.raises(ApiError) as err:
        c.get_session("s1")
    assert err.value.status == 503 and err.value.detail == "database away"
    assert len(seen) == 5 and len(sleeps) == 4
    caps = [1.0, 2.0, 4.0, 5.0]
    assert all(0.1 * cap <= s <= cap for s, cap in zip(sleeps, caps, strict=True)), sleeps
    assert len(set(sleeps)) == 4  # jittered, not a fixed ladder


def test_connect_errors_are_retried_for_every_call(sleeps: list[float]) -> None:
    transport, seen = scripted([fail(httpx.ConnectError), fail(httpx.ConnectError),
                                httpx.Response(201, json=PATIENT)])
    with Client("http://t", "tok", transport=transport) as c:
        assert c.create_patient(display_name="x").id == "p1"
    assert len(seen) == 3 and len(sleeps) == 2


def test_a_lost_answer_is_resent_only_when_resending_is_safe(sleeps: list[float]) -> None:
    # Creating a patient twice would create two patients: a read timeout is not retried.
    transport, seen = scripted([fail(httpx.ReadTimeout), httpx.Response(201, json=PATIENT)])
    with Client("http://t", "tok", transport=transport) as c, pytest.raises(httpx.ReadTimeout):
        c.create_patient(display_name="x")
    assert len(seen) == 1
    # A batch is idempotent per (sensor_id, seq): resent, and the replay is acknowledged.
    transport, seen = scripted([fail(httpx.ReadTimeout), httpx.Response(200, json={**BATCH_OK, "duplicate": True})])
    with Client("http://t", "tok", transport=transport) as c:
        assert c.upload_batch("s1", BATCH).duplicate
    assert len(seen) == 2 and seen[0].content == seen[1].content


def test_retry_after_beyond_the_limit_is_not_waited_for(sleeps: list[float]) -> None:
    transport, seen = scripted([httpx.Response(429, json=PROBLEM, headers={"Retry-After": "3600"})])
    with Client("http://t", "tok", transport=transport) as c, pytest.raises(ApiError) as err:
        c.upload_batch("s1", BATCH)
    assert err.value.status == 429 and err.value.retry_after_s == 3600 and not sleeps


def test_batches_are_gzip_by_default_and_plain_on_request(sleeps: list[float]) -> None:
    transport, seen = scripted([httpx.Response(201, json=BATCH_OK), httpx.Response(201, json=BATCH_OK)])
    with Client("http://t", "tok", transport=transport) as c:
        c.upload_batch("s1", BATCH)
        c.upload_batch("s1", BATCH, gzip=False)
    assert seen[0].headers["content-encoding"] == "gzip"
    assert json.loads(gzip.decompress(seen[0].content)) == BATCH
    assert "content-encoding" not in seen[1].headers and json.loads(seen[1].content) == BATCH
    assert seen[0].headers["authorization"] == "Bearer tok"


def test_non_problem_error_bodies_still_raise_a_readable_api_error(sleeps: list[float]) -> None:
    transport, _ = scripted([httpx.Response(404, text="<html>nginx</html>", headers={"X-Request-ID": "r1"})])
    with Client("http://t", "tok", transport=transport) as c, pytest.raises(ApiError) as err:
        c.get_session("s1")
    assert (err.value.status, err.value.title, err.value.detail) == (404, "Not Found", "<html>nginx</html>")
    assert "r1" in str(err.value)


def test_async_client_retries_like_the_sync_one(monkeypatch: pytest.MonkeyPatch) -> None:
    slept: list[float] = []

    async def fake_sleep(s: float) -> None:
        slept.append(s)

    monkeypatch.setattr("gaitmon.client.async_.asyncio.sleep", fake_sleep)

    async def handler(request: httpx.Request) -> httpx.Response:
        if len(slept) < 2:
            raise httpx.ConnectError("down", request=request)
        return httpx.Response(201, json=BATCH_OK)

    async def run() -> bool:
        async with AsyncClient("http://t", "tok", transport=httpx.MockTransport(handler)) as c:
            return (await c.upload_batch("s1", BATCH)).duplicate

    assert asyncio.run(run()) is False
    assert len(slept) == 2


def test_to_dataframe_without_pandas_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    strides = Strides(session_id="s1", strides=())
    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ImportError, match="pip install"):
        strides.to_dataframe()
