"""Upload load on a real server: batches per second, request latency, and time from /complete to done.

    .venv/bin/python -m bench.ingest                         # SQLite (embedded jobs), 4 phones x 2 minutes
    .venv/bin/python -m bench.ingest --postgres              # PostgreSQL + one `gaitmon worker`
    .venv/bin/python -m bench.ingest --phones 8 --minutes 5 --batch-size 25

Starts ``gaitmon serve`` (and on PostgreSQL ``gaitmon worker``) on 127.0.0.1 with a fresh database, creates a
clinician, and per simulated phone a patient, a device token and a two-leg session. Each phone uploads its gzip'd
batches from its own thread in upload order, as an app on a live BLE stream would; then every session is completed
and the time until ``done`` is measured. Only loopback traffic; every wait is bounded.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from gaitmon.client import Client
from pipeline.simulate import SimConfig, simulate_session
from server.simulate_cli import session_to_requests


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gaitmon() -> list[str]:
    script = Path(sys.executable).with_name("gaitmon")
    return [str(script)] if script.exists() else [sys.executable, "-m", "server.cli"]


def _fresh_pg(admin_url: str, name: str) -> str:
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    admin.dispose()
    return make_url(admin_url).set(database=name).render_as_string(hide_password=False)


def _wait_healthy(base: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError("server did not become healthy")


def _phone(base: str, token: str, create: dict, batches: list[dict]) -> tuple[str, list[float]]:
    """One app: create the session, upload its batches one after the other; returns id and latencies (s)."""
    latencies: list[float] = []
    with Client(base, token, timeout_s=60) as client:
        sid = client.create_session(**create).id
        for body in batches:
            t0 = time.perf_counter()
            client.upload_batch(sid, body)
            latencies.append(time.perf_counter() - t0)
    return sid, latencies


def run(args: argparse.Namespace) -> None:
    tmp = Path(tempfile.mkdtemp(prefix="gaitmon-bench-ingest-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("GAITMON_")}
    env["GAITMON_DATA_DIR"] = str(tmp / "data")
    env["GAITMON_LOG_LEVEL"] = "WARNING"
    # Every simulated phone shares 127.0.0.1: a per-address limit would measure the limit, not the server.
    # The per-token limit stays on (each phone has its own token, as in the field).
    env["GAITMON_RATE_LIMIT_PER_IP"] = ""
    if args.postgres:
        env["GAITMON_DATABASE_URL"] = _fresh_pg(args.pg_url, args.pg_db)
        env["GAITMON_JOB_RUNNER"] = "procrastinate"
    db_label = "PostgreSQL (+1 worker)" if args.postgres else "SQLite (embedded jobs)"
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    procs: list[subprocess.Popen] = []
    logs = (tmp / "server.log").open("wb")
    clinician: Client | None = None
    try:
        subprocess.run(_gaitmon() + ["migrate"], env=env, check=True, capture_output=True, timeout=120)
        procs.append(subprocess.Popen(_gaitmon() + ["serve", "--port", str(port)], env=env, stdout=logs,
                                      stderr=subprocess.STDOUT))
        if args.postgres:
            procs.append(subprocess.Popen(_gaitmon() + ["worker"], env=env, stdout=logs, stderr=subprocess.STDOUT))
        _wait_healthy(base)
        admin = subprocess.run(_gaitmon() + ["create-token", "--role", "admin"], env=env, check=True,
                               capture_output=True, text=True, timeout=60).stdout.strip().splitlines()[-1]
        with Client(base, admin) as as_admin:
            clin_token = as_admin.create_clinician("bench").token
        clinician = Client(base, clin_token, timeout_s=30)

        _log(f"simulating {args.phones} sessions of {args.minutes:g} min at {args.fs:g} Hz ...")
        phones = []
        for k in range(args.phones):
            pid = clinician.create_patient(display_name=f"p{k}").id
            dev = clinician.create_device_token(pid).token
            sim = simulate_session(SimConfig(pattern="normal", fs_hz=args.fs, duration_s=60 * args.minutes,
                                             seed=200 + k))
            create, batches = session_to_requests(sim, batch_size=args.batch_size, patient_id=pid,
                                                  client_session_id=f"bench-{k}")
            phones.append((dev, create, batches))
        n_batches = sum(len(b) for _, _, b in phones)
        n_samples = sum(len(x["gyro"]) for _, _, b in phones for x in b)
        _log(f"uploading {n_batches} batches ({n_samples} samples) from {args.phones} phones in parallel ...")
        t0 = time.perf_counter()
        with ThreadPoolExecutor(max_workers=args.phones) as pool:
            results = list(pool.map(lambda p: _phone(base, *p), phones))
        upload_s = time.perf_counter() - t0
        lat_ms = sorted(1000 * x for _, lats in results for x in lats)

        _log("completing the sessions and waiting for processing ...")
        t1 = time.perf_counter()
        for (dev, _, _), (sid, _) in zip(phones, results, strict=True):
            with Client(base, dev) as phone:
                phone.complete_session(sid)
        pending = {sid for sid, _ in results}
        deadline = time.monotonic() + args.timeout_s
        strides = 0
        while pending and time.monotonic() < deadline:
            for sid in list(pending):
                s = clinician.get_session(sid)
                if s.finished:
                    pending.discard(sid)
                    legs = (s.summary or {}).get("legs", {})
                    strides += sum(v.get("n_strides", 0) for v in legs.values())
            time.sleep(0.2)
        process_s = time.perf_counter() - t1
        if pending:
            raise RuntimeError(f"{len(pending)} sessions not processed within {args.timeout_s} s")

        def pct(q: float) -> float:
            return lat_ms[min(len(lat_ms) - 1, int(q * len(lat_ms)))]

        recorded_s = args.phones * 60 * args.minutes
        print(f"## Upload load: {db_label}\n")
        print(f"{args.phones} phones x {args.minutes:g} min two-leg sessions at {args.fs:g} Hz, "
              f"{args.batch_size} samples per batch, gzip, one connection per phone, batches sent one after the "
              f"other (2-core machine, server and clients on it).\n")
        print("| figure | value |\n|---|---|")
        print(f"| batches stored | {n_batches} ({n_samples} samples) |")
        print(f"| throughput | {n_batches / upload_s:.0f} batches/s, {n_samples / upload_s:,.0f} samples/s |")
        print(f"| batch latency p50 / p95 / max | {statistics.median(lat_ms):.1f} / {pct(0.95):.1f} / "
              f"{lat_ms[-1]:.1f} ms |")
        print(f"| real time uploaded per wall second | {recorded_s / upload_s:.0f} s of recording |")
        print(f"| complete -> all {args.phones} sessions done | {process_s:.1f} s ({strides} strides) |")
    finally:
        if clinician is not None:
            clinician.close()
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        logs.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.ingest", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--phones", type=int, default=4)
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--postgres", action="store_true")
    ap.add_argument("--pg-url", default="postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
    ap.add_argument("--pg-db", default="gaitmon_bench_ingest")
    ap.add_argument("--timeout-s", type=float, default=300.0)
    run(ap.parse_args(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
