"""Many phones against one real server: acknowledged, refused (503) and failed batches, latency, and afterwards
from the database the samples lost (acknowledged but not stored) and doubled (stored twice or never sent).

    .venv/bin/python -m bench.load                                   # SQLite embedded, 20 phones x 20 s
    .venv/bin/python -m bench.load --postgres --phones 200 --seconds 60
    .venv/bin/python -m bench.load --postgres --phones 500 --seconds 60
    .venv/bin/python -m bench.load --postgres --api-workers 2 --phones 200 --seconds 30
    .venv/bin/python -m bench.load --postgres --phones 50 --seconds 40 --kill   # kill -9 API and worker twice
    .venv/bin/python -m bench.load --memory                          # 8 x 8 MB bodies at once: API RSS
    .venv/bin/python -m bench.load --postgres --phones 200 --probe DIR  # + where slow uploads wait (bench.load_probe)

Each phone is an asyncio task per sensor (``--sensors`` per phone, default 2: thigh and shank of one leg) sending
one gzip'd batch per second (``--fs`` samples) in seq order, as the app's upload queue does: a 503 or 429 is retried
after its ``Retry-After``, a dropped connection after a short back-off, until ``--seconds`` plus a drain of at
most ``--drain-s``. The phones use the lean keep-alive client of :mod:`bench.http1` (a connection each), and the
generator reports its own event-loop lag: that much of every latency it measures is its own, not the server's.
``/healthz`` is sampled every 0.5 s on a connection of its own. The server is uvicorn on
127.0.0.1 (``--api-workers`` processes) with a fresh database; on PostgreSQL a ``gaitmon worker`` runs too.

Reference: a bare FastAPI endpoint that inflates and validates the same gzip'd body the same way (a thread each,
no database), run with the same number of processes; both are driven by ``--saturate`` closed-loop clients for
``--saturate-s`` seconds each, in ``--saturate-rounds`` alternating slices (the machine is shared), and the ratio of
acknowledged batches/s is printed. Loopback only; every wait bounded.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gzip
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import anyio
import httpx
import numpy as np
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from sqlalchemy import create_engine, text

from bench.http1 import Http1Connection, Http1Error
from bench.ingest import _free_port, _fresh_pg, _gaitmon, _log, _wait_healthy
from server.sessions.schemas import BatchIn

REPO = Path(__file__).resolve().parents[1]
# The longest Retry-After a phone honours here (the app's client honours up to 120 s; the run is shorter).
MAX_RETRY_AFTER_S = 10.0
# --probe: every upload carries its wall-clock send time (bench.load_probe lines it up with the server's records).
PROBE_SEND_TIME = False
SEGMENTS = [("left", "thigh"), ("left", "shank"), ("right", "thigh"), ("right", "shank")]


def bare_app():  # noqa: ANN201 - the reference app (uvicorn --factory bench.load:bare_app)
    """A FastAPI app with one endpoint doing what the upload costs without a database: inflate, validate."""
    app = FastAPI()

    @app.post("/bare/batches", status_code=201)
    async def bare(request: Request) -> JSONResponse:
        raw = await request.body()
        if request.headers.get("content-encoding") == "gzip":
            raw = await anyio.to_thread.run_sync(zlib.decompress, raw, 16 + zlib.MAX_WBITS)
        body = await anyio.to_thread.run_sync(BatchIn.model_validate_json, raw)
        return JSONResponse({"sensor_id": body.sensor_id, "seq": body.seq, "samples": len(body.gyro)},
                            status_code=201)

    return app


@dataclass
class Stats:
    """What the phones saw."""

    statuses: Counter = field(default_factory=Counter)
    ack_latency_ms: list[float] = field(default_factory=list)
    refused_latency_ms: list[float] = field(default_factory=list)
    health_ms: list[float] = field(default_factory=list)
    health_fail: int = 0
    conn_errors: int = 0
    retry_after_missing: int = 0
    # (session_id, sensor_id) -> seqs acknowledged / sent at least once, samples per batch
    acked: dict[tuple[str, str], set[int]] = field(default_factory=dict)
    sent: dict[tuple[str, str], set[int]] = field(default_factory=dict)
    unfinished: int = 0
    # How late this load generator's event loop woke up for a 50 ms sleep: its share of every latency above
    loop_lag_ms: list[float] = field(default_factory=list)
    # CPU seconds while the phones ran: the API processes, and this load generator (same 2 cores)
    api_cpu_s: float = 0.0
    generator_cpu_s: float = 0.0
    # --probe: (wall-clock send time, ms, status) of every answer slower than bench.load_probe.SLOW_S
    slow: list[tuple[float, float, int]] = field(default_factory=list)


_SAMPLES_JSON: dict[tuple[float, int], bytes] = {}


def batch_bytes(sensor_id: str, seq: int, fs_hz: float, rng: np.random.Generator) -> bytes:
    """One second of samples of one sensor, gzip'd JSON as the app sends it.

    The sample values come from a few pre-rendered variants: the load generator shares the 2 cores with the
    server, so it should spend its time sending, not formatting numbers.
    """
    n = int(fs_hz)
    variant = int(rng.integers(8))
    key = (fs_hz, variant)
    if key not in _SAMPLES_JSON:
        vr = np.random.default_rng(variant)
        _SAMPLES_JSON[key] = json.dumps({"gyro": np.round(vr.normal(0, 80, (n, 3)), 2).tolist(),
                                         "acc": np.round(vr.normal(0, 9.81, (n, 3)), 3).tolist()},
                                        separators=(",", ":")).encode()[1:]
    head = json.dumps({"sensor_id": sensor_id, "seq": seq, "t0_ms": seq * 1000.0}, separators=(",", ":"))
    return gzip.compress(head.encode()[:-1] + b"," + _SAMPLES_JSON[key], compresslevel=1)


def pct(values: list[float], q: float) -> float:
    """The q-quantile (nearest rank) or NaN."""
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


class Server:
    """The API (uvicorn, N processes) and on PostgreSQL one worker, each in a process group of its own."""

    def __init__(self, env: dict[str, str], port: int, workers: int, postgres: bool, log_path: Path,
                 app: str = "server.app:create_app", cwd: Path = REPO) -> None:
        self.env, self.port, self.workers, self.postgres, self.app = env, port, workers, postgres, app
        # ``python -m uvicorn`` puts its working directory first on sys.path: it decides which code is served.
        self.cwd = cwd
        self.log = log_path.open("ab")
        self.api: subprocess.Popen | None = None
        self.worker: subprocess.Popen | None = None

    def start(self) -> None:
        cmd = [sys.executable, "-m", "uvicorn", self.app, "--factory", "--host", "127.0.0.1", "--port",
               str(self.port), "--workers", str(self.workers), "--no-access-log", "--log-level", "warning"]
        self.api = subprocess.Popen(cmd, env=self.env, stdout=self.log, stderr=subprocess.STDOUT,
                                    start_new_session=True, cwd=self.cwd)
        if self.postgres and self.app.startswith("server."):
            self.worker = subprocess.Popen(_gaitmon() + ["worker"], env=self.env, stdout=self.log,
                                           stderr=subprocess.STDOUT, start_new_session=True, cwd=self.cwd)

    def kill9(self) -> None:
        for p in (self.api, self.worker):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)

    def stop(self) -> None:
        for p in (self.api, self.worker):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in (self.api, self.worker):
            if p is None:
                continue
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)

    def _group_pids(self) -> list[int]:
        pids = []
        for pid_dir in Path("/proc").iterdir():
            if pid_dir.name.isdigit():
                try:
                    if self.api is not None and os.getpgid(int(pid_dir.name)) == self.api.pid:
                        pids.append(int(pid_dir.name))
                except (OSError, ProcessLookupError):
                    continue
        return pids

    def cpu_s(self) -> float:
        """CPU seconds used so far by the API processes (user + system)."""
        return sum(_proc_cpu_s(pid) for pid in self._group_pids())

    def rss_mb(self) -> float:
        """Resident memory of the API processes (the uvicorn process group), MB."""
        total = 0
        for pid in self._group_pids():
            try:
                for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1])
            except OSError:
                continue
        return total / 1024.0


async def _retrying(client: httpx.AsyncClient | Http1Connection, method: str, url: str, stats: Stats,
                    deadline: float, **kw) -> httpx.Response | None:  # noqa: ANN003
    """Send until an answer other than 429/503 or the deadline; those wait Retry-After, a dropped connection 0.5-1 s."""
    while time.monotonic() < deadline:
        t0 = time.perf_counter()
        wall0 = time.time()
        if PROBE_SEND_TIME and "headers" in kw:
            kw["headers"] = {**kw["headers"], "X-Probe-Sent": f"{wall0:.6f}"}
        try:
            r = await client.request(method, url, **kw)
        except (httpx.HTTPError, Http1Error):
            stats.conn_errors += 1
            stats.slow.append((wall0, 1000 * (time.perf_counter() - t0), 0))
            await asyncio.sleep(0.5 + random.random() * 0.5)
            continue
        ms = 1000 * (time.perf_counter() - t0)
        stats.statuses[r.status_code] += 1
        if ms >= 250:
            stats.slow.append((wall0, ms, r.status_code))
        if r.status_code in (429, 503):
            # "Not now", nothing was done: retried after Retry-After, as the app's client does.
            stats.refused_latency_ms.append(ms)
            ra = r.headers.get("retry-after")
            if ra is None:
                stats.retry_after_missing += 1
            await asyncio.sleep(min(float(ra or 1), MAX_RETRY_AFTER_S) * (0.5 + random.random()))
            continue
        if r.status_code in (200, 201):
            stats.ack_latency_ms.append(ms)
        return r
    return None


async def _sensor_loop(base: str, sid: str, sensor_id: str, token: str, args: argparse.Namespace,
                       t_start: float, stats: Stats) -> None:
    # A connection per sensor, as on a phone, on the lean client of bench.http1: with httpx (~1 ms CPU per request)
    # 200+ phones in one event loop delay their own sends and answers by hundreds of ms.
    client = _connection(base)
    try:
        await _sensor_uploads(client, sid, sensor_id, token, args, t_start, stats)
    finally:
        client.close()


def _connection(base: str) -> Http1Connection:
    url = urlsplit(base)
    return Http1Connection(url.hostname or "127.0.0.1", url.port or 80, timeout_s=30)


async def _lag_loop(stop: asyncio.Event, stats: Stats, period_s: float = 0.05) -> None:
    while not stop.is_set():
        t0 = time.perf_counter()
        await asyncio.sleep(period_s)
        stats.loop_lag_ms.append(1000 * (time.perf_counter() - t0 - period_s))


async def _sensor_uploads(client: Http1Connection, sid: str, sensor_id: str, token: str,
                          args: argparse.Namespace, t_start: float, stats: Stats) -> None:
    rng = np.random.default_rng(abs(hash((sid, sensor_id))) % 2**32)
    # Accept-Encoding as a phone's HTTP stack (OkHttp, NSURLSession) sends it: the server's response gzip layer runs.
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json", "Content-Encoding": "gzip",
               "Accept-Encoding": "gzip"}
    acked = stats.acked.setdefault((sid, sensor_id), set())
    sent = stats.sent.setdefault((sid, sensor_id), set())
    hard_deadline = t_start + args.seconds + args.drain_s
    seq = 0
    # Phones start spread over the first second, as they would be in a clinic.
    next_t = t_start + random.random()
    while next_t < t_start + args.seconds:
        await asyncio.sleep(max(0.0, next_t - time.monotonic()))
        data = batch_bytes(sensor_id, seq, args.fs, rng)
        sent.add(seq)
        r = await _retrying(client, "POST", f"/v1/sessions/{sid}/batches", stats, hard_deadline, content=data,
                            headers=headers)
        if r is None:
            stats.unfinished += 1
            return
        if r.status_code in (200, 201):
            acked.add(seq)
        seq += 1
        next_t += 1.0


async def _provision(base: str, admin: str, n: int, sensors: int, fs: float) -> list[tuple[str, str, list[str]]]:
    """n patients with a device token and a session each: (token, session id, sensor ids)."""
    stats = Stats()
    deadline = time.monotonic() + 300
    async with httpx.AsyncClient(base_url=base, timeout=30) as c:
        h = {"Authorization": f"Bearer {admin}"}
        r = await _retrying(c, "POST", "/v1/clinicians", stats, deadline, json={"name": "load"}, headers=h)
        hc = {"Authorization": f"Bearer {r.json()['token']}"}
        sem = asyncio.Semaphore(8)
        declared = [{"sensor_id": f"{leg[0].upper()}-{seg}", "leg": leg, "segment": seg, "sample_rate_hz": fs}
                    for leg, seg in SEGMENTS[:sensors]]

        async def one(k: int) -> tuple[str, str, list[str]]:
            async with sem:
                p = await _retrying(c, "POST", "/v1/patients", stats, deadline, json={"display_name": f"p{k}"},
                                    headers=hc)
                pid = p.json()["id"]
                t = await _retrying(c, "POST", f"/v1/patients/{pid}/device-tokens", stats, deadline, headers=hc)
                tok = t.json()["token"]
                s = await _retrying(c, "POST", "/v1/sessions", stats, deadline, headers={
                    "Authorization": f"Bearer {tok}"}, json={
                    "patient_id": pid, "client_session_id": f"load-{k}", "started_at": "2026-11-30T08:00:00Z",
                    "sensors": declared})
                return tok, s.json()["id"], [d["sensor_id"] for d in declared]

        return list(await asyncio.gather(*(one(k) for k in range(n))))


def _health_thread(base: str, stop: threading.Event, stats: Stats) -> None:
    # A thread of its own with a blocking client: the sample is not delayed by the phones' event loop.
    with httpx.Client(base_url=base, timeout=10) as c:
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                if c.get("/healthz").status_code != 200:
                    stats.health_fail += 1
            except httpx.HTTPError:
                stats.health_fail += 1
            stats.health_ms.append(1000 * (time.perf_counter() - t0))
            stop.wait(0.5)


async def _killer(server: Server, base: str, args: argparse.Namespace, t_start: float) -> int:
    kills = 0
    for frac in (1 / 3, 2 / 3):
        await asyncio.sleep(max(0.0, t_start + frac * args.seconds - time.monotonic()))
        _log(f"kill -9 of the API and the worker at t={time.monotonic() - t_start:.1f} s")
        await asyncio.to_thread(server.kill9)
        await asyncio.sleep(1.0)
        await asyncio.to_thread(server.start)
        kills += 1
    return kills


async def _rss_loop(server: Server, stop: asyncio.Event, peak: list[float]) -> None:
    while not stop.is_set():
        peak[0] = max(peak[0], await asyncio.to_thread(server.rss_mb))
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 0.5)


async def drive_phones(base: str, phones: list[tuple[str, str, list[str]]], args: argparse.Namespace,
                       server: Server) -> tuple[Stats, float, float]:
    """Run the phones; returns their stats, the wall time and the API's peak RSS (MB)."""
    stats = Stats()
    cpu0, gen0 = server.cpu_s(), _own_cpu_s()
    stop = asyncio.Event()
    health_stop = threading.Event()
    peak = [0.0]
    t_start = time.monotonic()
    health = threading.Thread(target=_health_thread, args=(base, health_stop, stats), daemon=True)
    health.start()
    side = [asyncio.create_task(_rss_loop(server, stop, peak))]
    side.append(asyncio.create_task(_lag_loop(stop, stats)))
    killer = asyncio.create_task(_killer(server, base, args, t_start)) if args.kill else None
    await asyncio.gather(*(_sensor_loop(base, sid, sensor, tok, args, t_start, stats)
                           for tok, sid, sensors in phones for sensor in sensors))
    wall = time.monotonic() - t_start
    if killer is not None:
        await killer
    stop.set()
    health_stop.set()
    await asyncio.gather(*side)
    health.join(timeout=15)
    stats.api_cpu_s, stats.generator_cpu_s = server.cpu_s() - cpu0, _own_cpu_s() - gen0
    return stats, wall, peak[0]


def _proc_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of one process so far; 0 once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def postgres_cpu_s() -> float:
    """CPU seconds used so far by every PostgreSQL process of this machine (server, backends, WAL writer,
    checkpointer), read from /proc: what the database costs per batch, without pg_stat_statements. Backends that
    ended since the last reading are not counted, so it is a lower bound; other databases' clients count too."""
    total = 0.0
    for pid_dir in Path("/proc").iterdir():
        if not pid_dir.name.isdigit():
            continue
        try:
            if (pid_dir / "comm").read_text().strip() != "postgres":
                continue
        except OSError:
            continue
        total += _proc_cpu_s(int(pid_dir.name))
    return total


def _own_cpu_s() -> float:
    """CPU seconds of this process (the phones and the /healthz thread), user + system."""
    t = os.times()
    return t.user + t.system


@dataclass
class Saturated:
    """What closed-loop senders got from one server: acknowledged batches, seconds, the server's CPU seconds, the
    database's CPU seconds (:func:`postgres_cpu_s`; 0 without PostgreSQL) and the load generator's."""

    acked: int = 0
    seconds: float = 0.0
    cpu_s: float = 0.0
    db_cpu_s: float = 0.0
    generator_cpu_s: float = 0.0

    def add(self, other: Saturated) -> None:
        self.acked += other.acked
        self.seconds += other.seconds
        self.cpu_s += other.cpu_s
        self.db_cpu_s += other.db_cpu_s
        self.generator_cpu_s += other.generator_cpu_s

    @property
    def per_s(self) -> float:
        return self.acked / max(self.seconds, 1e-9)

    @property
    def cpu_ms(self) -> float:
        """The server's CPU milliseconds per acknowledged batch (a figure that holds on a shared machine)."""
        return 1000 * self.cpu_s / max(self.acked, 1)

    @property
    def db_cpu_ms(self) -> float:
        return 1000 * self.db_cpu_s / max(self.acked, 1)

    @property
    def generator_cpu_ms(self) -> float:
        return 1000 * self.generator_cpu_s / max(self.acked, 1)


async def saturate(base: str, path_for: list[tuple[str, str, str]], seconds: float, clients: int,
                   fs: float, server: Server, first_seq: int = 100_000) -> Saturated:
    """Closed loop: ``clients`` senders posting new batches (seq from ``first_seq`` on) back to back."""
    acked = 0
    cpu0, db0, gen0 = server.cpu_s(), postgres_cpu_s() if server.postgres else 0.0, _own_cpu_s()
    deadline = time.monotonic() + seconds

    async def sender(k: int) -> None:
        nonlocal acked
        url, sensor_id, token = path_for[k % len(path_for)]
        rng = np.random.default_rng(k)
        headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json",
                   "Content-Encoding": "gzip", "Accept-Encoding": "gzip"}
        seq = first_seq + k * 100_000
        c = _connection(base)
        try:
            while time.monotonic() < deadline:
                try:
                    r = await c.request("POST", url, content=batch_bytes(sensor_id, seq, fs, rng), headers=headers)
                except Http1Error:
                    await asyncio.sleep(0.05)
                    continue
                seq += 1
                if r.status_code in (200, 201):
                    acked += 1
        finally:
            c.close()

    t0 = time.monotonic()
    await asyncio.gather(*(sender(k) for k in range(clients)))
    db_s = postgres_cpu_s() - db0 if server.postgres else 0.0
    return Saturated(acked, time.monotonic() - t0, server.cpu_s() - cpu0, db_s, _own_cpu_s() - gen0)


async def saturate_both(base: str, targets: list[tuple[str, str, str]], server: Server, bare_base: str,
                        bare: Server, args: argparse.Namespace) -> tuple[Saturated, Saturated]:
    """gaitmon and the bare endpoint in ``--saturate-rounds`` alternating slices of the ``--saturate-s`` each
    gets: the load of the machine's other tenants drifts, and alternating shares its drift between the two."""
    ours, theirs = Saturated(), Saturated()
    rounds = max(1, args.saturate_rounds)
    for r in range(rounds):
        # Fresh seq numbers every round: every batch is new, none a replay.
        ours.add(await saturate(base, targets, args.saturate_s / rounds, args.saturate, args.fs, server,
                                first_seq=100_000 + r * 10_000))
        theirs.add(await saturate(bare_base, [("/bare/batches", "L-thigh", "x")], args.saturate_s / rounds,
                                  args.saturate, args.fs, bare))
    return ours, theirs


def db_check(url: str, stats: Stats) -> dict[str, int]:
    """Lost: acknowledged batches (samples) missing from the database. Doubled: a (sensor, seq) stored twice, or
    a stored batch that was never sent."""
    engine = create_engine(url)
    with engine.connect() as conn:
        rows = conn.execute(text("SELECT session_id, sensor_id, seq, n_samples FROM batches")).all()
    engine.dispose()
    stored: Counter = Counter()
    samples: dict[tuple[str, str, int], int] = {}
    for sid, sensor, seq, n in rows:
        stored[(sid, sensor, seq)] += 1
        samples[(sid, sensor, seq)] = n
    lost = doubled = never_sent = 0
    for key, seqs in stats.acked.items():
        for seq in seqs:
            if (key[0], key[1], seq) not in stored:
                lost += 1
    for (sid, sensor, seq), count in stored.items():
        doubled += count - 1
        if (sid, sensor) in stats.sent and seq not in stats.sent[(sid, sensor)]:
            never_sent += 1
    return {"stored_batches": len(stored), "stored_samples": sum(samples.values()), "lost_batches": lost,
            "doubled_batches": doubled + never_sent}


def _env(tmp: Path, args: argparse.Namespace) -> tuple[dict[str, str], str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GAITMON_")}
    env["GAITMON_DATA_DIR"] = str(tmp / "data")
    env["GAITMON_LOG_LEVEL"] = "WARNING"
    env["PYTHONPATH"] = str(args.server_repo or REPO) + os.pathsep + env.get("PYTHONPATH", "")
    # Every simulated phone connects from 127.0.0.1; real phones have addresses of their own, so the per-address
    # limit (GAITMON_RATE_LIMIT_PER_IP, 200/s by default) would refuse here what it never would in a clinic.
    # The per-token limit applies as configured. --env GAITMON_RATE_LIMIT_PER_IP=... overrides this.
    env["GAITMON_RATE_LIMIT_PER_IP"] = "1000000/minute"
    for kv in args.env:
        k, _, v = kv.partition("=")
        env[k] = v
    if args.postgres:
        url = _fresh_pg(args.pg_url, f"gaitmon_load_{os.getpid()}")
        env["GAITMON_DATABASE_URL"] = url
        env["GAITMON_JOB_RUNNER"] = "procrastinate"
    else:
        url = f"sqlite:///{(tmp / 'data' / 'gaitmon.sqlite').resolve()}"
    return env, url


async def memory_probe(base: str, token: str, sid: str, server: Server, n: int = 8) -> dict[str, float]:
    """``n`` bodies of 8 MB (a million rows, over the sample limit) at once, plain and gzip'd: API RSS (MB)."""
    rows = 1_000_000
    body = (b'{"sensor_id":"L-thigh","seq":1,"t0_ms":0,"gyro":[' + b"[1,2,3]," * (rows - 1) + b'[1,2,3]],"acc":[]}')
    body = body[: 8 * 1024 * 1024 - 16] if len(body) > 8 * 1024 * 1024 else body
    gz = gzip.compress(body)
    before = server.rss_mb()
    stop = asyncio.Event()
    peak = [before]
    statuses: Counter = Counter()
    t0 = time.perf_counter()
    async with httpx.AsyncClient(base_url=base, timeout=60) as c:
        rss = asyncio.create_task(_rss_loop(server, stop, peak))
        for data, extra in ((body, {}), (gz, {"Content-Encoding": "gzip"})):
            rs = await asyncio.gather(*(c.post(f"/v1/sessions/{sid}/batches", content=data, headers={
                "Authorization": f"Bearer {token}", "Content-Type": "application/json", **extra})
                for _ in range(n)), return_exceptions=True)
            for r in rs:
                statuses[getattr(r, "status_code", type(r).__name__)] += 1
        stop.set()
        await rss
    return {"rss_before_mb": before, "rss_peak_mb": peak[0], "seconds": time.perf_counter() - t0,
            "statuses": dict(statuses), "body_bytes": len(body), "gzip_bytes": len(gz)}


def _admin_token(env: dict[str, str]) -> str:
    out = subprocess.run(_gaitmon() + ["create-token", "--role", "admin"], env=env, check=True,
                         capture_output=True, text=True, timeout=120, cwd=REPO)
    return out.stdout.strip().splitlines()[-1]


def run(args: argparse.Namespace) -> dict:
    """One load run; prints a Markdown table and returns the figures."""
    tmp = Path(tempfile.mkdtemp(prefix="gaitmon-load-"))
    env, url = _env(tmp, args)
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    probe_dir: Path | None = args.probe
    if probe_dir is not None:
        global PROBE_SEND_TIME  # noqa: PLW0603 - the phones' coroutines read it
        PROBE_SEND_TIME = True
        probe_dir.mkdir(parents=True, exist_ok=True)
        env["GAITMON_PROBE_FILE"] = str(probe_dir / "server.jsonl")
    server = Server(env, port, args.api_workers, args.postgres, tmp / "server.log",
                    app="bench.load_probe:create_app" if probe_dir is not None else "server.app:create_app",
                    cwd=(args.server_repo or REPO).resolve())
    out: dict = {}
    try:
        if probe_dir is not None and args.postgres:
            # This benchmark database only: slow statements in the server log, WAL write/fsync times counted.
            admin = create_engine(args.pg_url, isolation_level="AUTOCOMMIT")
            with admin.connect() as conn:
                name = url.rsplit("/", 1)[1]
                conn.execute(text(f'ALTER DATABASE "{name}" SET log_min_duration_statement = 200'))
                conn.execute(text(f'ALTER DATABASE "{name}" SET log_lock_waits = on'))
                conn.execute(text(f'ALTER DATABASE "{name}" SET track_wal_io_timing = on'))
            admin.dispose()
        subprocess.run(_gaitmon() + ["migrate"], env=env, check=True, capture_output=True, timeout=180, cwd=REPO)
        admin = _admin_token(env)
        server.start()
        _wait_healthy(base)
        phones = asyncio.run(_provision(base, admin, args.phones, args.sensors, args.fs))
        if args.memory:
            out["memory"] = asyncio.run(memory_probe(base, phones[0][0], phones[0][1], server))
            print(json.dumps(out["memory"], indent=1))
            return out
        _log(f"{args.phones} phones x {args.sensors} sensors, 1 batch/s of {args.fs:g} samples, {args.seconds} s")
        sampler_stop = threading.Event()
        samplers: list[threading.Thread] = []
        if probe_dir is not None:
            from bench.load_probe import pg_sampler, proc_sampler

            pids = {"worker": server.worker.pid if server.worker else None, "api": server.api.pid if server.api
                    else None}
            samplers.append(threading.Thread(target=proc_sampler, args=(pids, str(probe_dir / "procs.jsonl"),
                                                                        sampler_stop), daemon=True))
            if args.postgres:
                samplers.append(threading.Thread(target=pg_sampler, args=(url, str(probe_dir / "pg.jsonl"),
                                                                          sampler_stop), daemon=True))
            for th in samplers:
                th.start()
        _log(f"phones start at {time.time():.3f} (epoch s)")
        stats, wall, peak = asyncio.run(drive_phones(base, phones, args, server))
        sampler_stop.set()
        for th in samplers:
            th.join(timeout=10)
        if probe_dir is not None:
            (probe_dir / "client_slow.json").write_text(json.dumps(stats.slow))
        check = db_check(url, stats)
        acked = sum(len(v) for v in stats.acked.values())
        five = sum(v for k, v in stats.statuses.items() if k >= 500 and k != 503)
        out.update(phones=args.phones, sensors=args.sensors, seconds=args.seconds, acked=acked,
                   sent=sum(len(v) for v in stats.sent.values()), statuses=dict(stats.statuses),
                   five_xx_not_503=five, refused_503=stats.statuses.get(503, 0),
                   refused_429=stats.statuses.get(429, 0), conn_errors=stats.conn_errors,
                   unfinished=stats.unfinished, retry_after_missing=stats.retry_after_missing,
                   ack_p50_ms=pct(stats.ack_latency_ms, 0.5), ack_p99_ms=pct(stats.ack_latency_ms, 0.99),
                   ack_max_ms=max(stats.ack_latency_ms, default=float("nan")),
                   refused_p99_ms=pct(stats.refused_latency_ms, 0.99),
                   health_p99_ms=pct(stats.health_ms, 0.99), generator_lag_p99_ms=pct(stats.loop_lag_ms, 0.99),
                   generator_lag_max_ms=max(stats.loop_lag_ms, default=float("nan")),
                   health_max_ms=max(stats.health_ms, default=0.0),
                   health_fail=stats.health_fail, api_rss_peak_mb=peak, wall_s=wall,
                   api_cpu_ms_per_ack=1000 * stats.api_cpu_s / max(acked, 1),
                   api_cores=stats.api_cpu_s / wall, generator_cores=stats.generator_cpu_s / wall, **check)
        if args.saturate:
            targets = [(f"/v1/sessions/{sid}/batches", sensors[0], tok) for tok, sid, sensors in phones]
            bare_port = _free_port()
            bare = Server(env, bare_port, args.api_workers, False, tmp / "bare.log", app="bench.load:bare_app")
            bare.start()
            bare_base = f"http://127.0.0.1:{bare_port}"
            try:
                _wait_bare(bare_base)
                ours, theirs = asyncio.run(saturate_both(base, targets, server, bare_base, bare, args))
            finally:
                bare.stop()
            out["gaitmon_batches_per_s"], out["gaitmon_cpu_ms"] = ours.per_s, ours.cpu_ms
            out["bare_batches_per_s"], out["bare_cpu_ms"] = theirs.per_s, theirs.cpu_ms
            out["ratio"] = out["gaitmon_batches_per_s"] / out["bare_batches_per_s"]
            out["cpu_ratio"] = out["bare_cpu_ms"] / out["gaitmon_cpu_ms"]
            out["gaitmon_db_cpu_ms"] = ours.db_cpu_ms
            out["gaitmon_generator_cpu_ms"] = ours.generator_cpu_ms
            out["bare_generator_cpu_ms"] = theirs.generator_cpu_ms
        _print(out, args)
        return out
    finally:
        server.stop()


def _wait_bare(base: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            httpx.get(f"{base}/docs", timeout=2)
            return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise RuntimeError("bare server did not start")


def _print(o: dict, args: argparse.Namespace) -> None:
    db = "PostgreSQL + 1 worker" if args.postgres else "SQLite (embedded jobs)"
    print(f"\n## Load: {o['phones']} phones x {o['sensors']} sensors, {args.seconds} s, {args.api_workers} API "
          f"process(es), {db}{', kill -9 twice' if args.kill else ''}\n")
    print("| figure | value |\n|---|---|")
    print(f"| batches sent / acknowledged | {o['sent']} / {o['acked']} |")
    print(f"| answers | {', '.join(f'{k}: {v}' for k, v in sorted(o['statuses'].items()))} |")
    print(f"| 5xx other than 503 | {o['five_xx_not_503']} |")
    print(f"| 503 / 429 (refused, retried) / p99 answer time | {o['refused_503']} / {o['refused_429']} / "
          f"{o['refused_p99_ms']:.0f} ms |")
    print(f"| dropped connections (retried) | {o['conn_errors']} |")
    print(f"| batches given up at the deadline | {o['unfinished']} |")
    print(f"| ack latency p50 / p99 / max | {o['ack_p50_ms']:.0f} / {o['ack_p99_ms']:.0f} / {o['ack_max_ms']:.0f} ms |")
    print(f"| /healthz p99 / max (failures) | {o['health_p99_ms']:.0f} / {o['health_max_ms']:.0f} ms "
          f"({o['health_fail']}) |")
    print(f"| load generator's own event-loop lag p99 / max | {o['generator_lag_p99_ms']:.0f} / "
          f"{o['generator_lag_max_ms']:.0f} ms |")
    print(f"| lost / doubled batches (database) | {o['lost_batches']} / {o['doubled_batches']} |")
    print(f"| API peak RSS | {o['api_rss_peak_mb']:.0f} MB |")
    print(f"| API CPU per acknowledged batch / cores used: API, load generator | {o['api_cpu_ms_per_ack']:.2f} ms / "
          f"{o['api_cores']:.2f}, {o['generator_cores']:.2f} |")
    if "ratio" in o:
        print(f"| saturated: gaitmon / bare endpoint | {o['gaitmon_batches_per_s']:.0f} / "
              f"{o['bare_batches_per_s']:.0f} batches/s = {o['ratio']:.2f} |")
        print(f"| API CPU per batch: gaitmon / bare endpoint | {o['gaitmon_cpu_ms']:.2f} / {o['bare_cpu_ms']:.2f} ms "
              f"(bare/gaitmon = {o['cpu_ratio']:.2f}) |")
        if args.postgres:
            print(f"| PostgreSQL CPU per gaitmon batch (all its processes) | {o['gaitmon_db_cpu_ms']:.2f} ms |")
        print(f"| load generator CPU per batch: gaitmon / bare endpoint | {o['gaitmon_generator_cpu_ms']:.2f} / "
              f"{o['bare_generator_cpu_ms']:.2f} ms |")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of the benchmark."""
    ap = argparse.ArgumentParser(prog="python -m bench.load", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--phones", type=int, default=20)
    ap.add_argument("--sensors", type=int, default=2, choices=[1, 2, 3, 4])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--api-workers", type=int, default=1)
    ap.add_argument("--postgres", action="store_true")
    ap.add_argument("--kill", action="store_true", help="kill -9 the API and the worker at 1/3 and 2/3 of the run")
    ap.add_argument("--drain-s", type=float, default=30.0)
    ap.add_argument("--saturate", type=int, default=0, help="closed-loop clients for the bare-endpoint ratio")
    ap.add_argument("--saturate-s", type=float, default=10.0, help="seconds of closed loop for each server")
    ap.add_argument("--saturate-rounds", type=int, default=4,
                    help="alternating slices gaitmon / bare endpoint the --saturate-s are cut into")
    ap.add_argument("--memory", action="store_true", help="only the 8 x 8 MB body probe")
    ap.add_argument("--env", action="append", default=[], help="GAITMON_X=value for the server")
    ap.add_argument("--pg-url", default="postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
    ap.add_argument("--server-repo", type=Path, default=None,
                    help="serve the code of another checkout (to compare with an earlier version)")
    ap.add_argument("--json", action="store_true", help="also print the figures as JSON")
    ap.add_argument("--probe", type=Path, default=None,
                    help="directory for bench.load_probe's records: the server's event-loop lag, thread pool, "
                         "pool checkouts, GC pauses and slow uploads, PostgreSQL's waits, the phones' slow answers")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = run(args)
    if args.json:
        print(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
