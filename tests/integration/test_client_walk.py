"""gaitmon.client (sync and async) against a real `gaitmon serve` on a free localhost port (SQLite, embedded jobs).

The walk: create patient -> session (and again: same session) -> upload (a replay, plain and gzip bodies) ->
complete -> wait -> strides -> trends, plus typed errors; then /metrics shows what the walk did, and /docs,
/redoc work with every asset served by the same server.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from html.parser import HTMLParser
from pathlib import Path

import httpx
import pytest

from gaitmon.client import ApiError, AsyncClient, Client
from pipeline.simulate import SimConfig, simulate_session
from server.simulate_cli import session_to_requests, truth_summary
from tests.integration.conftest import free_port, gaitmon_command, server_env

pytestmark = pytest.mark.xdist_group("client-walk")  # one server for the module


class Server:
    def __init__(self, tmp: Path) -> None:
        self.env = server_env(tmp, None)
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.log_path = tmp / "server.log"
        self._log = self.log_path.open("wb")
        self.popen = subprocess.Popen(gaitmon_command() + ["serve", "--port", str(self.port)], env=self.env,
                                      cwd=tmp, stdout=self._log, stderr=subprocess.STDOUT)
        self.cwd = tmp

    def tail(self) -> str:
        return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-40:])

    def wait_healthy(self) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            assert self.popen.poll() is None, f"server exited:\n{self.tail()}"
            try:
                if httpx.get(f"{self.base}/healthz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"server not healthy:\n{self.tail()}")

    def admin_token(self) -> str:
        res = subprocess.run(gaitmon_command() + ["create-token", "--role", "admin"], env=self.env, cwd=self.cwd,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        return res.stdout.strip().splitlines()[-1]

    def stop(self) -> None:
        self.popen.terminate()
        try:
            self.popen.wait(20)
        except subprocess.TimeoutExpired:
            self.popen.kill()
        self._log.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(tmp_path_factory.mktemp("client-walk"))
    try:
        srv.wait_healthy()
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="module")
def clinician_token(server: Server) -> str:
    with Client(server.base, server.admin_token()) as admin:
        assert admin.me().role == "admin"
        return admin.create_clinician("Dr Client").token


def recording(seed: int, client_session_id: str) -> tuple[dict, list[dict], dict]:
    sim = simulate_session(SimConfig(n_strides=14, seed=seed))
    create, batches = session_to_requests(sim, batch_size=100, patient_id="-", client_session_id=client_session_id,
                                          started_at=datetime(2026, 11, 20, 10, 0, tzinfo=UTC))
    return create, batches, truth_summary(sim)


def metric_value(text: str, name: str, **labels: str) -> float:
    want = ",".join(f'{k}="{v}"' for k, v in sorted(labels.items()))
    total = 0.0
    for line in text.splitlines():
        m = re.match(r"^(\w+)(?:\{(.*)\})? (\S+)$", line)
        if not m or m.group(1) != name:
            continue
        got = ",".join(sorted((m.group(2) or "").split(","))) if m.group(2) else ""
        if all(f'{k}="{v}"' in got for k, v in labels.items()) or (not want and not got):
            total += float(m.group(3))
    return total


def check_strides_and_trends(strides_by_leg: dict, trends, truth: dict) -> None:  # noqa: ANN001
    for leg, strides in strides_by_leg.items():
        n_true = truth[leg]["n_strides"]
        # The detector may drop the first or last stride of a recording, never invent many.
        assert n_true - 3 <= len(strides.strides) <= n_true + 1, (leg, len(strides.strides), n_true)
        assert all(s.leg == leg for s in strides.strides)
        df = strides.to_dataframe()
        assert len(df) == len(strides.strides) and "peak_swing_flexion_deg" in df.columns
        assert df["peak_swing_flexion_deg"].between(20, 90).all()
    assert trends.metric == "peak_swing_flexion_deg" and trends.leg == "left"
    assert len(trends.buckets) == 1 and trends.buckets[0].n_sessions >= 1
    assert 0 < trends.buckets[0].n_strides <= len(strides_by_leg["left"].strides) * trends.buckets[0].n_sessions
    tdf = trends.to_dataframe()
    assert list(tdf["n_strides"]) == [b.n_strides for b in trends.buckets]


def test_sync_client_walks_the_contract_and_metrics_count_it(server: Server, clinician_token: str) -> None:
    before = httpx.get(f"{server.base}/metrics").text
    create, batches, truth = recording(seed=11, client_session_id="client-sync-1")
    with Client(server.base, clinician_token) as clin:
        patient = clin.create_patient(display_name="Sync", external_id="MRN-100")
        assert patient.external_id == "MRN-100"
        device = clin.create_device_token(patient.id, "phone")
        with Client(server.base, device.token) as phone:
            sess = phone.create_session(patient.id, create["client_session_id"], create["started_at"],
                                        create["sensors"])
            again = phone.create_session(patient.id, create["client_session_id"], create["started_at"],
                                         create["sensors"])
            assert again.id == sess.id and sess.status == "receiving"
            half = len(batches) // 2
            plain = [phone.upload_batch(sess.id, b, gzip=False) for b in batches[:half]]
            zipped = phone.upload_batches(sess.id, batches[half:], concurrency=3)
            assert not any(r.duplicate for r in plain + zipped)
            replay = phone.upload_batch(sess.id, batches[0])
            assert replay.duplicate and replay.samples == len(batches[0]["gyro"])
            with pytest.raises(ApiError) as conflict:
                changed = dict(batches[1], gyro=[[v + 1.0 for v in row] for row in batches[1]["gyro"]])
                phone.upload_batch(sess.id, changed)
            assert conflict.value.status == 409 and conflict.value.request_id
            with pytest.raises(ApiError) as bad:
                phone.upload_batch(sess.id, dict(batches[2], gyro=batches[2]["gyro"][:-1]))
            assert bad.value.status == 422 and bad.value.errors and bad.value.title == "Validation failed"
            received = phone.get_session(sess.id).received
            assert sum(r.batches for r in received.values()) == len(batches)
            assert phone.complete_session(sess.id).status in ("queued", "processing", "done")
        done = clin.wait_for_processing(sess.id, timeout_s=120, poll_s=0.3)
        assert done.status == "done", (done.error, server.tail())
        strides = {leg: clin.get_strides(sess.id, leg=leg) for leg in ("left", "right")}
        trends = clin.get_trends(patient.id, leg="left")
        check_strides_and_trends(strides, trends, truth)
        with pytest.raises(ApiError) as missing:
            clin.get_session("no-such-session")
        assert missing.value.status == 404

    after = httpx.get(f"{server.base}/metrics").text
    n_samples = sum(len(b["gyro"]) for b in batches)

    def delta(name: str, **labels: str) -> float:
        return metric_value(after, name, **labels) - metric_value(before, name, **labels)

    assert delta("gaitmon_batches_total", result="stored") == len(batches)
    assert delta("gaitmon_batches_total", result="duplicate") == 1
    assert delta("gaitmon_samples_ingested_total") == n_samples
    assert delta("gaitmon_jobs_total", outcome="done") == 1
    assert delta("gaitmon_job_duration_seconds_count", outcome="done") == 1
    route = "/v1/sessions/{session_id}/batches"
    assert delta("gaitmon_http_requests_total", method="POST", route=route, status="201") == len(batches)
    assert delta("gaitmon_http_requests_total", method="POST", route=route, status="409") == 1
    assert delta("gaitmon_http_request_duration_seconds_count", method="POST", route=route) == len(batches) + 3
    assert sess.id not in after  # route templates, never raw paths
    assert re.search(r'^gaitmon_sessions_in_queue\{status="queued"\} 0\.0$', after, re.M)


def test_async_client_walks_the_contract(server: Server, clinician_token: str) -> None:
    create, batches, truth = recording(seed=12, client_session_id="client-async-1")

    async def walk() -> tuple[dict, object]:
        async with AsyncClient(server.base, clinician_token) as clin:
            patient = await clin.create_patient(display_name="Async")
            device = await clin.create_device_token(patient.id)
            async with AsyncClient(server.base, device.token) as phone:
                sess = await phone.create_session(patient.id, create["client_session_id"], create["started_at"],
                                                  create["sensors"])
                results = await phone.upload_batches(sess.id, batches, concurrency=4)
                assert [r.seq for r in results] == [b["seq"] for b in batches]
                replays = await phone.upload_batches(sess.id, batches[:3])
                assert all(r.duplicate for r in replays)
                await phone.complete_session(sess.id)
                # Completing again is safe (the client may resend after a lost answer).
                await phone.complete_session(sess.id)
            done = await clin.wait_for_processing(sess.id, timeout_s=120, poll_s=0.3)
            assert done.status == "done", done.error
            strides = {leg: await clin.get_strides(sess.id, leg=leg) for leg in ("left", "right")}
            return strides, await clin.get_trends(patient.id, leg="left")

    strides, trends = asyncio.run(walk())
    check_strides_and_trends(strides, trends, truth)


class _Assets(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "script" and a.get("src"):
            self.urls.append(a["src"] or "")
        if tag == "link" and a.get("href"):
            self.urls.append(a["href"] or "")


def test_docs_and_every_asset_come_from_this_server(server: Server) -> None:
    for page in ("/docs", "/redoc"):
        resp = httpx.get(server.base + page)
        assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/html")
        parser = _Assets()
        parser.feed(resp.text)
        scripts = [u for u in parser.urls if u.endswith(".js")]
        assert scripts, f"{page} references no script"
        for url in parser.urls:
            assert url.startswith("/"), f"{page} loads {url} from another host"
            asset = httpx.get(server.base + url)
            assert asset.status_code == 200 and len(asset.content) > 1000, url
        assert not re.search(r"https?://(?!127\.0\.0\.1)", "".join(re.findall(r"<(?:script|link)[^>]*>", resp.text)))
    assert httpx.get(server.base + "/openapi.json").status_code == 200


def test_every_response_and_log_line_carries_a_request_id(server: Server) -> None:
    mine = httpx.get(f"{server.base}/v1/me", headers={"X-Request-ID": "trace-abc.123"})
    assert mine.status_code == 401 and mine.headers["x-request-id"] == "trace-abc.123"
    insane = httpx.get(f"{server.base}/healthz", headers={"X-Request-ID": "x" * 300})
    generated = insane.headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", generated)
    deadline = time.monotonic() + 5
    while "trace-abc.123" not in server.log_path.read_text() and time.monotonic() < deadline:
        time.sleep(0.1)
    lines = server.log_path.read_text().splitlines()
    assert any("[trace-abc.123]" in line and "/v1/me" in line for line in lines), server.tail()
    assert any(f"[{generated}]" in line for line in lines)
