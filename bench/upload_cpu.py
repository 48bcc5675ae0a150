"""CPU per uploaded batch in process: the real ASGI app (every middleware, the route, PostgreSQL or SQLite) and
the bare reference endpoint of :mod:`bench.load` beside it, driven the same way in the same run.

    .venv/bin/python -m bench.upload_cpu --postgres                 # CPU ms per batch, app and bare endpoint
    .venv/bin/python -m bench.upload_cpu --postgres --profile 30    # + the 30 costliest functions (yappi)

No HTTP server and no socket: each request is one ASGI call (scope, receive, send) from ``--concurrency`` tasks on
one event loop, so the figure is the application's own cost; uvicorn's parsing and the kernel's come on top in
:mod:`bench.load`. CPU is the process's (every thread), so thread hops are counted; the database server's is not.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench.ingest import _fresh_pg
from bench.load import bare_app, batch_bytes

Asgi = Callable[[dict, Callable[[], Awaitable[dict]], Callable[[dict], Awaitable[None]]], Awaitable[None]]


async def asgi_call(app: Asgi, method: str, path: str, headers: dict[str, str], body: bytes = b"",
                    ) -> tuple[int, bytes]:
    """One HTTP request as a single ASGI call; the status and the body of the answer."""
    raw_headers = [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    if body:
        raw_headers.append((b"content-length", str(len(body)).encode()))
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method, "scheme": "http",
             "path": path, "raw_path": path.encode(), "root_path": "", "query_string": b"", "headers": raw_headers,
             "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 8000), "state": {}}
    sent = False
    status = 0
    out = bytearray()

    async def receive() -> dict:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.sleep(3600)  # a client that keeps the connection open
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        nonlocal status
        if message["type"] == "http.response.start":
            status = message["status"]
        elif message["type"] == "http.response.body":
            out.extend(message.get("body", b""))

    await app(scope, receive, send)
    return status, bytes(out)


async def _json(app: Asgi, method: str, path: str, token: str, payload: Any = None) -> dict:
    body = json.dumps(payload).encode() if payload is not None else b""
    headers = {"authorization": f"Bearer {token}"}
    if body:
        headers["content-type"] = "application/json"
    status, out = await asgi_call(app, method, path, headers, body)
    if status not in (200, 201):
        raise RuntimeError(f"{method} {path} -> {status}: {out[:300]!r}")
    return json.loads(out)


async def provision(app: Asgi, admin: str, n: int, fs_hz: float) -> list[tuple[str, str]]:
    """``n`` patients with a device token and a one-sensor session each: (token, session id)."""
    clinician = (await _json(app, "POST", "/v1/clinicians", admin, {"name": "cpu"}))["token"]
    out = []
    for k in range(n):
        pid = (await _json(app, "POST", "/v1/patients", clinician, {"display_name": f"p{k}"}))["id"]
        tok = (await _json(app, "POST", f"/v1/patients/{pid}/device-tokens", clinician))["token"]
        s = await _json(app, "POST", "/v1/sessions", tok, {
            "patient_id": pid, "client_session_id": f"cpu-{k}", "started_at": "2026-11-30T08:00:00Z",
            "sensors": [{"sensor_id": "L-thigh", "leg": "left", "segment": "thigh", "sample_rate_hz": fs_hz}]})
        out.append((tok, s["id"]))
    return out


async def drive(app: Asgi, targets: list[tuple[str, str]], batches: int, concurrency: int, fs_hz: float,
                first_seq: int) -> tuple[float, float, Counter]:
    """``batches`` new batches from ``concurrency`` tasks (one target each); CPU and wall ms per batch."""
    bodies: dict[tuple[int, int], bytes] = {}
    rng = np.random.default_rng(0)
    per_task = batches // concurrency
    for k in range(concurrency):
        for i in range(per_task):
            bodies[(k, i)] = batch_bytes("L-thigh", first_seq + i, fs_hz, rng)
    statuses: Counter = Counter()

    async def task(k: int) -> None:
        token, sid = targets[k % len(targets)]
        headers = {"authorization": f"Bearer {token}", "content-type": "application/json",
                   "content-encoding": "gzip"}
        for i in range(per_task):
            status, _ = await asgi_call(app, "POST", f"/v1/sessions/{sid}/batches", headers, bodies[(k, i)])
            statuses[status] += 1

    cpu0, wall0 = time.process_time(), time.perf_counter()
    await asyncio.gather(*(task(k) for k in range(concurrency)))
    n = per_task * concurrency
    return 1000 * (time.process_time() - cpu0) / n, 1000 * (time.perf_counter() - wall0) / n, statuses


def _bare_asgi() -> Asgi:
    app = bare_app()

    async def as_bare(scope: dict, receive: Callable, send: Callable) -> None:
        # The same bodies at the bare endpoint's path.
        await app(dict(scope, path="/bare/batches", raw_path=b"/bare/batches"), receive, send)

    return as_bare


def _profile_start() -> Any:  # noqa: ANN401 - the yappi module, when installed
    try:
        import yappi
    except ImportError:
        print("(yappi is not installed: `.venv/bin/pip install yappi` for --profile)")
        return None
    yappi.set_clock_type("cpu")
    yappi.clear_stats()
    yappi.start(builtins=False, profile_threads=True)
    return yappi


def _profile_print(yappi: Any, top: int, total_batches: int) -> None:  # noqa: ANN401
    yappi.stop()
    stats = yappi.get_func_stats()
    rows = sorted(stats, key=lambda s: s.ttot, reverse=True)[:top]
    print("\n| function | inclusive CPU us per batch | own CPU us per batch | calls per batch |\n|---|---|---|---|")
    for s in rows:
        where = s.module.split("site-packages/")[-1].split("wt-")[-1]
        print(f"| {s.name} ({where}:{s.lineno}) | {1e6 * s.ttot / total_batches:.0f} | "
              f"{1e6 * s.tsub / total_batches:.0f} | {s.ncall / total_batches:.1f} |")


async def run(args: argparse.Namespace) -> dict[str, Any]:
    """Both measurements, in rounds alternating app and bare endpoint (the machine is shared)."""
    from server.app import create_app
    from server.auth.service import issue_token
    from server.config import Settings
    from server.migrate import upgrade_to_head

    tmp = Path(tempfile.mkdtemp(prefix="gaitmon-cpu-"))
    url = _fresh_pg(args.pg_url, "gaitmon_upload_cpu") if args.postgres else f"sqlite:///{tmp / 'gaitmon.sqlite'}"
    upgrade_to_head(url)
    settings = Settings(database_url=url, data_dir=tmp, job_runner="manual", log_level="WARNING")
    app = create_app(settings)
    with app.state.sessionmaker() as db:
        _, admin = issue_token(db, role="admin", name="cpu")
        db.commit()
    bare = _bare_asgi()
    out: dict[str, Any] = {"app_cpu_ms": [], "bare_cpu_ms": [], "app_wall_ms": [], "bare_wall_ms": []}
    async with app.router.lifespan_context(app):
        targets = await provision(app, admin, args.concurrency, args.fs)
        await drive(app, targets, args.concurrency * 20, args.concurrency, args.fs, 0)  # warm caches, pools
        await drive(bare, targets, args.concurrency * 20, args.concurrency, args.fs, 0)
        seq = 1000
        profiler = _profile_start() if args.profile else None
        for _ in range(args.rounds):
            cpu, wall, statuses = await drive(app, targets, args.batches, args.concurrency, args.fs, seq)
            if set(statuses) != {201}:
                raise RuntimeError(f"uploads were not all stored: {dict(statuses)}")
            out["app_cpu_ms"].append(cpu)
            out["app_wall_ms"].append(wall)
            seq += args.batches
            if profiler is None:
                cpu, wall, _ = await drive(bare, targets, args.batches, args.concurrency, args.fs, seq)
                out["bare_cpu_ms"].append(cpu)
                out["bare_wall_ms"].append(wall)
        if profiler is not None:
            _profile_print(profiler, args.profile, args.rounds * args.batches)
    app.state.engine.dispose()
    return out


def _print(out: dict[str, Any], args: argparse.Namespace) -> None:
    db = "PostgreSQL" if args.postgres else "SQLite"
    print(f"\n## Upload CPU in process ({db}, {args.concurrency} concurrent, {args.rounds} x {args.batches} batches "
          f"of {args.fs:g} samples, gzip)\n")
    print("| | median CPU ms per batch | min | median wall ms per batch |\n|---|---|---|---|")
    for name in ("app", "bare"):
        cpu = out[f"{name}_cpu_ms"]
        if cpu:
            print(f"| {'gaitmon upload' if name == 'app' else 'bare endpoint'} | {np.median(cpu):.3f} | "
                  f"{min(cpu):.3f} | {np.median(out[f'{name}_wall_ms']):.3f} |")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of the benchmark."""
    ap = argparse.ArgumentParser(prog="python -m bench.upload_cpu", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--postgres", action="store_true")
    ap.add_argument("--pg-url", default="postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
    ap.add_argument("--batches", type=int, default=800, help="batches per round and endpoint")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--concurrency", type=int, default=16)
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--profile", type=int, default=0, help="print this many functions by CPU (yappi; app only)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = asyncio.run(run(args))
    _print(out, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
