"""Where a slow upload spends its time, measured inside the API process (``bench.load --probe``).

``uvicorn --factory bench.load_probe:create_app`` serves the ordinary app with probes around it; every record is
one JSON line in ``$GAITMON_PROBE_FILE`` with the wall-clock time ``t`` (seconds since the epoch), so it lines up
with the load generator's slow answers and the PostgreSQL samples of :func:`pg_sampler`:

- ``loop``: every 20 ms, how late the event loop woke up, and the thread pool's busy and waiting tasks;
- ``gc``: every Python collection of 10 ms or more (``gc.callbacks``);
- ``req``: every upload slower than :data:`SLOW_S` inside the app, split into arrival -> thread start (body,
  auth, waiting for a thread), pool checkout, the INSERT, thread end -> answer sent.

Only the benchmark uses this module; the served code is unchanged.
"""

from __future__ import annotations

import asyncio
import contextvars
import gc
import json
import os
import threading
import time
from pathlib import Path
from typing import Any

import anyio

SLOW_S = 0.25
# The load generator's wall-clock send time of a request (bench.load --probe sends it).
PROBE_HEADER = b"x-probe-sent"
_LOOP_PERIOD_S = 0.02

_arrival: contextvars.ContextVar[dict[str, float] | None] = contextvars.ContextVar("probe_arrival", default=None)


class _Sink:
    def __init__(self, path: str) -> None:
        self._f = open(path, "a", buffering=1)  # noqa: SIM115 - lives as long as the process
        self._lock = threading.Lock()

    def write(self, **rec: Any) -> None:  # noqa: ANN401
        line = json.dumps(rec)
        with self._lock:
            self._f.write(line + "\n")


def create_app():  # noqa: ANN201 - uvicorn --factory
    from server import app as app_module
    from server.sessions import routes

    sink = _Sink(os.environ.get("GAITMON_PROBE_FILE", "probe.jsonl"))
    _patch_uvicorn()
    app = app_module.create_app()
    engine = app.state.engine
    pool = engine.pool

    # Pool checkout (includes pre-ping and a new connection when one is made) and the INSERT, per thread.
    orig_checkout = type(pool)._do_get
    tls = threading.local()

    def timed_do_get(self):  # noqa: ANN001, ANN202
        t0 = time.perf_counter()
        try:
            return orig_checkout(self)
        finally:
            tls.checkout = getattr(tls, "checkout", 0.0) + time.perf_counter() - t0

    pool._do_get = timed_do_get.__get__(pool)
    orig_insert = routes.insert_batch

    def timed_insert(conn, stmt, params):  # noqa: ANN001, ANN202
        t0 = time.perf_counter()
        try:
            return orig_insert(conn, stmt, params)
        finally:
            tls.insert = time.perf_counter() - t0

    routes.insert_batch = timed_insert
    committer = getattr(app.state, "group_committer", None)
    if committer is not None:
        # On PostgreSQL the INSERT goes through the group committer: its time includes waiting for the group
        # being written before its own and the commit of the transaction holding it.
        orig_group_insert = committer.insert

        def timed_group_insert(sql, params):  # noqa: ANN001, ANN202
            t0 = time.perf_counter()
            try:
                return orig_group_insert(sql, params)
            finally:
                tls.insert = time.perf_counter() - t0

        committer.insert = timed_group_insert
    orig_upload = routes._upload

    def timed_upload(*a):  # noqa: ANN002, ANN202
        marks = _arrival.get()
        tls.checkout, tls.insert = 0.0, 0.0
        if marks is not None:
            marks["thread_start"] = time.time()
        try:
            return orig_upload(*a)
        finally:
            if marks is not None:
                marks["thread_end"] = time.time()
                marks["checkout"] = tls.checkout
                marks["insert"] = tls.insert

    routes._upload = timed_upload

    def gc_cb(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            tls.gc0 = time.perf_counter()
            return
        d = time.perf_counter() - getattr(tls, "gc0", time.perf_counter())
        if d >= 0.01:
            sink.write(kind="gc", t=time.time(), s=d, gen=info.get("generation"), collected=info.get("collected"))

    gc.callbacks.append(gc_cb)

    started = False

    async def loop_probe() -> None:
        limiter = anyio.to_thread.current_default_thread_limiter()
        while True:
            t0 = time.perf_counter()
            await asyncio.sleep(_LOOP_PERIOD_S)
            lag = time.perf_counter() - t0 - _LOOP_PERIOD_S
            st = limiter.statistics()
            sink.write(kind="loop", t=time.time(), lag=round(lag, 4), busy=st.borrowed_tokens,
                       waiting=st.tasks_waiting, pool_out=pool.checkedout(), tasks=len(asyncio.all_tasks()))

    async def probed(scope, receive, send) -> None:  # noqa: ANN001
        nonlocal started
        if not started and scope["type"] in ("http", "lifespan"):
            started = True
            asyncio.get_running_loop().create_task(loop_probe())
        if scope["type"] != "http" or not scope["path"].endswith("/batches"):
            await app(scope, receive, send)
            return
        marks = {"arrive": time.time()}
        sent = next((v for k, v in scope.get("headers", []) if k == PROBE_HEADER), None)
        begin = scope.get("probe_begin")
        _arrival.set(marks)
        status = 0

        async def watch(msg):  # noqa: ANN001, ANN202
            nonlocal status
            if msg["type"] == "http.response.start":
                status = msg["status"]
            await send(msg)

        await app(scope, receive, watch)
        done = time.time()
        t_sent = float(sent) if sent else marks["arrive"]
        if done - t_sent >= SLOW_S:
            sink.write(kind="req", t=marks["arrive"], total=done - marks["arrive"], status=status,
                       sent_to_parse=(begin or marks["arrive"]) - t_sent,
                       parse_to_app=marks["arrive"] - (begin or marks["arrive"]),
                       conn=scope.get("probe_conn"),
                       to_thread=marks.get("thread_start", done) - marks["arrive"],
                       in_thread=marks.get("thread_end", done) - marks.get("thread_start", done),
                       checkout=marks.get("checkout"), insert=marks.get("insert"),
                       after=done - marks.get("thread_end", done))

    return probed


def _patch_uvicorn() -> None:
    """Stamp every request with the time uvicorn's parser saw its first byte (``scope["probe_begin"]``)."""
    from uvicorn.protocols.http import h11_impl, httptools_impl

    proto = httptools_impl.HttpToolsProtocol
    orig_begin, orig_made = proto.on_message_begin, proto.connection_made

    def connection_made(self, transport) -> None:  # noqa: ANN001
        self.probe_made, self.probe_n = time.time(), 0
        orig_made(self, transport)

    def on_message_begin(self) -> None:  # noqa: ANN001
        orig_begin(self)
        self.probe_n += 1
        self.scope["probe_begin"] = time.time()
        self.scope["probe_conn"] = (self.probe_made, self.probe_n)

    proto.on_message_begin = on_message_begin
    proto.connection_made = connection_made
    del h11_impl


def pg_sampler(url: str, path: str, stop: threading.Event, period_s: float = 0.1) -> None:
    """Every ``period_s``: the benchmark database's non-idle backends (state, wait event, seconds in the query)
    and the background processes; every second pg_stat_bgwriter and pg_stat_wal. One JSON line each."""
    from sqlalchemy import create_engine, text

    engine = create_engine(url, isolation_level="AUTOCOMMIT")
    last_slow = 0.0
    with engine.connect() as conn, open(path, "a", buffering=1) as f:
        while not stop.is_set():
            now = time.time()
            rows = conn.execute(text(
                "SELECT backend_type, state, wait_event_type, wait_event, "
                "extract(epoch FROM clock_timestamp() - query_start) AS q_s, left(query, 60) AS q "
                "FROM pg_stat_activity WHERE pid <> pg_backend_pid() AND (datname = current_database() "
                "OR datname IS NULL) AND (state IS DISTINCT FROM 'idle' OR backend_type <> 'client backend')"
            )).mappings().all()
            acts = [dict(r) for r in rows if r["backend_type"] != "client backend" and r["wait_event"] not in (
                "CheckpointerMain", "BgWriterMain", "BgWriterHibernate", "WalWriterMain", "AutoVacuumMain",
                "LogicalLauncherMain", "ArchiverMain")]
            clients = [dict(r) for r in rows if r["backend_type"] == "client backend"]
            f.write(json.dumps({"kind": "pg", "t": now, "active": len(clients),
                                "waits": [[r["wait_event_type"], r["wait_event"], r["state"],
                                           round(float(r["q_s"] or 0), 3), r["q"]] for r in clients
                                          if (r["q_s"] or 0) > 0.2 or r["wait_event"]],
                                "bg": [[r["backend_type"], r["wait_event"], r["q"]] for r in acts]},
                               default=str) + "\n")
            if now - last_slow >= 1.0:
                last_slow = now
                bg = conn.execute(text("SELECT * FROM pg_stat_bgwriter")).mappings().one()
                wal = conn.execute(text("SELECT * FROM pg_stat_wal")).mappings().one()
                f.write(json.dumps({"kind": "pgstat", "t": now, "bgwriter": dict(bg), "wal": dict(wal)},
                                   default=str) + "\n")
            stop.wait(period_s)
    engine.dispose()


def proc_sampler(pids: dict[str, int | None], path: str, stop: threading.Event, period_s: float = 0.25) -> None:
    """Every ``period_s``: CPU seconds so far of each named process group (the API, the worker) and the machine's
    CPU and I/O pressure (``/proc/pressure``, "some" avg10 and total microseconds)."""
    tick = os.sysconf("SC_CLK_TCK")
    with open(path, "a", buffering=1) as f:
        while not stop.is_set():
            rec: dict[str, Any] = {"kind": "proc", "t": time.time(), "load": os.getloadavg()[0]}
            for name, pgid in pids.items():
                total = 0
                if pgid is not None:
                    for d in os.listdir("/proc"):
                        if not d.isdigit():
                            continue
                        try:
                            if os.getpgid(int(d)) != pgid:
                                continue
                            fields = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
                            total += int(fields[11]) + int(fields[12])
                        except (OSError, IndexError, ValueError):
                            continue
                rec[name] = total / tick
            for res in ("cpu", "io"):
                try:
                    some = Path(f"/proc/pressure/{res}").read_text().split()
                    rec[f"{res}_total_us"] = int(some[4].split("=")[1])
                except (OSError, IndexError, ValueError):
                    pass
            f.write(json.dumps(rec) + "\n")
            stop.wait(period_s)
