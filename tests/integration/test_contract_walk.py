"""A real server in a subprocess, walked through the HTTP contract (api-v1.md) by a plain HTTP client.

Two deployments: the single-process default (SQLite, jobs in the API process) and the multi-machine one
(PostgreSQL, the API only queues, two separate `gaitmon worker` processes do the work).
"""

from __future__ import annotations

import copy
import gzip
import json
import re
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from sqlalchemy import create_engine, text

from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from pipeline.types import RawSensorStream
from server.metadata import all_metadata
from server.simulate_cli import session_to_requests
from tests.integration.conftest import free_port, gaitmon_command, server_env

BATCH_SAMPLES = 40
WAIT_S = 120.0
PROBLEM = "application/problem+json"


class Proc:
    """A gaitmon subprocess with its output in a file (shown when an assertion fails)."""

    def __init__(self, args: list[str], env: dict[str, str], cwd: Path, log_path: Path) -> None:
        self.log_path = log_path
        self._log = log_path.open("wb")
        self.popen = subprocess.Popen(gaitmon_command() + args, env=env, cwd=cwd, stdout=self._log,
                                      stderr=subprocess.STDOUT)

    def tail(self, n: int = 40) -> str:
        lines = self.log_path.read_text(errors="replace").splitlines()
        return "\n".join(lines[-n:])

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.terminate()
            try:
                self.popen.wait(20)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(10)
        self._log.close()


@contextmanager
def processes() -> Iterator[list[Proc]]:
    procs: list[Proc] = []
    try:
        yield procs
    finally:
        for p in procs:
            p.stop()


def cli(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    res = subprocess.run(gaitmon_command() + args, env=env, cwd=cwd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    return res


def wait_healthy(client: httpx.Client, server: Proc) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert server.popen.poll() is None, f"server exited:\n{server.tail()}"
        try:
            if client.get("/healthz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise AssertionError(f"server not healthy within 60 s:\n{server.tail()}")


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def assert_problem(resp: httpx.Response, status: int | tuple[int, ...]) -> dict[str, Any]:
    statuses = (status,) if isinstance(status, int) else status
    assert resp.status_code in statuses, resp.text[:500]
    assert resp.headers["content-type"].startswith(PROBLEM)
    body = resp.json()
    assert {"type", "title", "status", "detail"} <= set(body) and body["status"] == resp.status_code
    assert "Traceback" not in resp.text
    return body


def assert_malformed_http_is_a_problem(base_url: str) -> None:
    """A request the HTTP parser refuses (a header line without a colon) gets a 400 problem document, then EOF."""
    host, port = base_url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(b"GET /v1/me HTTP/1.1\r\nHost: x\r\nno colon here\r\n\r\n")
        raw = b""
        while chunk := sock.recv(65536):  # the server closes the connection after answering
            raw += chunk
    head, _, body = raw.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    assert lines[0] == "HTTP/1.1 400 Bad Request", raw
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    assert headers["content-type"] == "application/problem+json" and headers["connection"] == "close"
    assert int(headers["content-length"]) == len(body)
    problem = json.loads(body)
    assert problem["status"] == 400 and problem["type"].endswith("malformed-request") and problem["detail"]


def streams_from_requests(create: dict[str, Any], batches: list[dict[str, Any]]) -> list[RawSensorStream]:
    """What the server must have assembled from these bodies (float32 samples), to predict its results exactly."""
    out = []
    for sensor in create["sensors"]:
        mine = sorted((b for b in batches if b["sensor_id"] == sensor["sensor_id"]), key=lambda b: b["seq"])
        t_ms = np.concatenate([b.get("timestamps_ms") or
                               b["t0_ms"] + np.arange(len(b["gyro"])) * 1000.0 / sensor["sample_rate_hz"]
                               for b in mine])
        gyro = np.concatenate([b["gyro"] for b in mine]).astype(np.float32).astype(np.float64)
        acc = np.concatenate([b["acc"] for b in mine]).astype(np.float32).astype(np.float64)
        order = np.argsort(t_ms, kind="stable")
        out.append(RawSensorStream(sensor["sensor_id"], sensor["leg"], sensor["segment"],
                                   float(sensor["sample_rate_hz"]), t_ms[order] / 1000.0, gyro[order], acc[order],
                                   sensor["gyro_unit"], sensor["acc_unit"]))
    return out


def post_gzip(client: httpx.Client, url: str, body: Any, token: str) -> httpx.Response:
    return client.post(url, content=gzip.compress(json.dumps(body).encode()),
                       headers={**auth(token), "Content-Type": "application/json", "Content-Encoding": "gzip"})


def wait_status(client: httpx.Client, sid: str, token: str, want: str, procs: list[Proc]) -> dict[str, Any]:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        body = client.get(f"/v1/sessions/{sid}", headers=auth(token)).json()
        if body["status"] == want:
            return body
        assert body["status"] != "failed", body
        time.sleep(0.25)
    logs = "\n\n".join(p.tail() for p in procs)
    raise AssertionError(f"session {sid} not {want} within {WAIT_S} s: {body}\n{logs}")


def rows_referring_to(db_url: str, session_id: str, patient_id: str) -> dict[str, int]:
    engine = create_engine(db_url)
    out = {}
    try:
        with engine.connect() as conn:
            for table in all_metadata().sorted_tables:
                checks = [("session_id", session_id), ("patient_id", patient_id)]
                checks += {"sessions": [("id", session_id)], "patients": [("id", patient_id)]}.get(table.name, [])
                for col, value in checks:
                    if col in table.c:
                        n = conn.execute(text(f'SELECT count(*) FROM "{table.name}" WHERE "{col}" = :v'),
                                         {"v": value}).scalar_one()
                        out[f"{table.name}.{col}"] = out.get(f"{table.name}.{col}", 0) + n
    finally:
        engine.dispose()
    return out


def db_worker_id(db_url: str, sid: str) -> str:
    engine = create_engine(db_url)
    try:
        with engine.connect() as conn:
            return conn.execute(text("SELECT worker_id FROM sessions WHERE id = :s"), {"s": sid}).scalar_one()
    finally:
        engine.dispose()


def walk(base_url: str, env: dict[str, str], cwd: Path, db_url: str, procs: list[Proc], worker_prefix: str) -> None:
    # Operator: the first admin token comes from the command line (last line of stdout).
    admin = cli(["create-token", "--role", "admin", "--name", "ops"], env, cwd).stdout.strip().splitlines()[-1]
    spare = cli(["create-token", "--role", "admin", "--name", "spare"], env, cwd)
    spare_token = spare.stdout.strip().splitlines()[-1]
    spare_id = re.search(r"created admin token ([0-9a-f]{32})", spare.stderr).group(1)
    cli(["revoke-token", spare_id], env, cwd)

    c = httpx.Client(base_url=base_url, timeout=30)
    assert_problem(c.get("/v1/patients"), 401)
    assert_problem(c.get("/v1/patients", headers=auth(spare_token)), 401)  # revoked on the command line
    assert_problem(c.get("/v1/no-such-route", headers=auth(admin)), 404)
    assert_malformed_http_is_a_problem(base_url)

    r = c.post("/v1/clinicians", json={"name": "Dr A", "email": "a@example.org"}, headers=auth(admin))
    assert r.status_code == 201, r.text
    clin = r.json()["token"]
    r = c.post("/v1/patients", json={"external_id": "P-001", "display_name": "Patient One", "affected_leg": "left",
                                     "timezone": "Europe/Berlin"}, headers=auth(clin))
    assert r.status_code == 201, r.text
    pid = r.json()["id"]
    r = c.post(f"/v1/patients/{pid}/device-tokens", headers=auth(clin))
    assert r.status_code == 201, r.text
    device = r.json()["token"]

    sim = simulate_session(SimConfig(n_strides=36, seed=11))
    body, batches = session_to_requests(sim, batch_size=BATCH_SAMPLES, patient_id=pid,
                                        started_at=datetime(2026, 11, 21, 9, 30, tzinfo=timezone(timedelta(hours=1))))
    r = c.post("/v1/sessions", json=body, headers=auth(device))
    assert r.status_code == 201 and r.json()["status"] == "receiving", r.text
    sid = r.json()["id"]
    r = c.post("/v1/sessions", json=body, headers=auth(device))  # the app retries after a timeout
    assert r.status_code == 200 and r.json()["id"] == sid

    # Upload: every batch, shuffled, 15 % of them twice, all gzip'd.
    rng = np.random.default_rng(5)
    order = [*range(len(batches)), *rng.choice(len(batches), size=len(batches) * 15 // 100, replace=False)]
    rng.shuffle(order)
    assert len(order) > 300
    seen: set[int] = set()
    for i in order:
        r = post_gzip(c, f"/v1/sessions/{sid}/batches", batches[i], device)
        assert r.status_code == (200 if i in seen else 201), r.text
        assert r.json()["samples"] == len(batches[i]["gyro"])
        seen.add(i)

    changed = copy.deepcopy(batches[3])
    changed["gyro"][0][0] += 1.0
    assert_problem(post_gzip(c, f"/v1/sessions/{sid}/batches", changed, device), 409)
    mismatch = {**copy.deepcopy(batches[0]), "seq": 100_000}
    mismatch["acc"] = mismatch["acc"][:-1]
    assert assert_problem(c.post(f"/v1/sessions/{sid}/batches", json=mismatch, headers=auth(device)), 422)["errors"]
    with_nan = {**copy.deepcopy(batches[0]), "seq": 100_001}
    with_nan["gyro"][2][1] = float("nan")
    raw = json.dumps(with_nan)  # Python writes the non-standard NaN literal, as sloppy clients do
    assert "NaN" in raw
    assert_problem(c.post(f"/v1/sessions/{sid}/batches", content=raw,
                          headers={**auth(device), "Content-Type": "application/json"}), (400, 422))

    state = c.get(f"/v1/sessions/{sid}", headers=auth(device)).json()
    assert state["status"] == "receiving"
    sent = streams_from_requests(body, batches)
    for s in sent:
        assert state["received"][s.sensor_id]["samples"] == len(s.t_s)
        assert state["received"][s.sensor_id]["batches"] == sum(b["sensor_id"] == s.sensor_id for b in batches)

    r = c.post(f"/v1/sessions/{sid}/complete", headers=auth(device))
    assert r.status_code == 202, r.text
    late = {**batches[0], "seq": 100_002}
    assert_problem(post_gzip(c, f"/v1/sessions/{sid}/batches", late, device), 409)

    done = wait_status(c, sid, device, "done", procs)
    assert done["algorithm_version"] and done["summary"]
    assert db_worker_id(db_url, sid).startswith(worker_prefix)

    # What the server computed equals the pipeline on the uploaded data: nothing lost, duplicated or reordered.
    expected = process_session(sent, activity=sim.activity)
    strides: dict[str, list[dict]] = {}
    for leg in ("left", "right"):
        r = c.get(f"/v1/sessions/{sid}/strides", params={"leg": leg}, headers=auth(clin))
        assert r.status_code == 200, r.text
        strides[leg] = r.json()["strides"]
        exp = expected.legs[leg].strides
        assert len(strides[leg]) == len(exp) > 10
        assert all(s["leg"] == leg for s in strides[leg])
        got_peaks = [s["peak_swing_flexion_deg"] for s in strides[leg]]
        assert np.allclose(got_peaks, [s.peak_swing_flexion_deg for s in exp], atol=1e-6)
        assert np.allclose([s["t_start_s"] for s in strides[leg]], [s.t_start_s for s in exp], atol=1e-9)
        truth_peak = np.median([s.peak_swing_flexion_deg for s in sim.truth[leg].strides])
        assert abs(np.median(got_peaks) - truth_peak) < 10.0

    r = c.get(f"/v1/sessions/{sid}/knee-angle", params={"leg": "left", "max_points": 500}, headers=auth(device))
    assert r.status_code == 200, r.text
    trace = r.json()
    assert 100 < len(trace["t_s"]) <= 500
    assert len(trace["angle_deg"]) == len(trace["estimator"]) == len(trace["t_s"])
    assert np.all(np.diff(trace["t_s"]) > 0)
    finite = [a for a in trace["angle_deg"] if a is not None]
    assert finite and min(finite) > -30 and max(finite) < 150

    assert_problem(c.post(f"/v1/sessions/{sid}/reprocess", headers=auth(device)), 403)
    r = c.post(f"/v1/sessions/{sid}/reprocess", headers=auth(clin))
    assert r.status_code == 202, r.text
    wait_status(c, sid, clin, "done", procs)
    for leg in ("left", "right"):
        again = c.get(f"/v1/sessions/{sid}/strides", params={"leg": leg}, headers=auth(clin)).json()["strides"]
        assert again == strides[leg]  # replaced, not appended

    # Another clinician cannot learn that the patient or the session exist.
    other = c.post("/v1/clinicians", json={"name": "Dr B"}, headers=auth(admin)).json()["token"]
    r = c.post("/v1/patients", json={"display_name": "B's patient"}, headers=auth(other))
    assert r.status_code == 201
    assert [p["id"] for p in c.get("/v1/patients", headers=auth(other)).json()["items"]] == [r.json()["id"]]
    assert_problem(c.get(f"/v1/patients/{pid}", headers=auth(other)), 404)
    assert_problem(c.get(f"/v1/sessions/{sid}", headers=auth(other)), 404)
    assert_problem(c.get(f"/v1/sessions/{sid}/strides", params={"leg": "left"}, headers=auth(other)), 404)
    assert_problem(c.delete(f"/v1/patients/{pid}", headers=auth(other)), 404)
    assert_problem(c.get(f"/v1/patients/{r.json()['id']}", headers=auth(device)), (403, 404))

    before = rows_referring_to(db_url, sid, pid)
    assert before["batches.session_id"] == len(batches) and before["strides.session_id"] > 20
    r = c.delete(f"/v1/patients/{pid}", headers=auth(clin))
    assert r.status_code in (200, 204), r.text
    assert_problem(c.get(f"/v1/patients/{pid}", headers=auth(clin)), 404)
    assert_problem(c.get(f"/v1/sessions/{sid}", headers=auth(clin)), 404)
    assert_problem(c.get(f"/v1/sessions/{sid}", headers=auth(device)), 401)  # its device token went with it
    after = rows_referring_to(db_url, sid, pid)
    assert after and all(n == 0 for n in after.values()), after
    c.close()


def test_walk_sqlite_single_process(tmp_path: Path) -> None:
    env = server_env(tmp_path, None)  # nothing configured: the README's one-command default
    port = free_port()
    with processes() as procs:
        server = Proc(["serve", "--port", str(port)], env, tmp_path, tmp_path / "serve.log")
        procs.append(server)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as c:
            wait_healthy(c, server)
        db_url = f"sqlite:///{tmp_path / 'data' / 'gaitmon.sqlite'}"
        walk(f"http://127.0.0.1:{port}", env, tmp_path, db_url, procs, "embedded@")
        assert re.search(r"jobs embedded", server.tail(10_000))
    assert server.popen.returncode is not None


@pytest.mark.postgres
def test_walk_postgres_with_separate_workers(tmp_path: Path, empty_pg_url: str) -> None:
    env = server_env(tmp_path, empty_pg_url)
    port = free_port()
    with processes() as procs:
        server = Proc(["serve", "--port", str(port)], env, tmp_path, tmp_path / "serve.log")
        procs.append(server)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as c:
            wait_healthy(c, server)  # serve migrated the empty database, queue schema included
        for i in range(2):
            procs.append(Proc(["worker"], env, tmp_path, tmp_path / f"worker{i}.log"))
        walk(f"http://127.0.0.1:{port}", env, tmp_path, empty_pg_url, procs, "worker@")
        assert re.search(r"jobs procrastinate", server.tail(10_000))
        logs = "".join(p.tail(10_000) for p in procs[1:])
        assert "done:" in logs  # the workers, not the API, processed the session
