"""A worker machine freezes mid-session (SIGSTOP: no heartbeat, no exit); another worker takes over, and when the
frozen one wakes up its late results are discarded. Real `gaitmon worker` processes on PostgreSQL."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text

from server.processing.worker import close_api_apps, defer_session
from tests.integration.conftest import gaitmon_command, insert_simulated_session, server_env

STALL_S = 2


def _session(url: str, sid: str) -> tuple[str, str | None, int, int]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            status, worker, attempts = conn.execute(
                text("SELECT status, worker_id, attempts FROM sessions WHERE id = :s"), {"s": sid}).one()
            n = conn.execute(text("SELECT count(*) FROM strides WHERE session_id = :s"), {"s": sid}).scalar_one()
            return status, worker, attempts, n
    finally:
        engine.dispose()


def _wait(predicate, timeout_s: float, what: str, logs: list[Path], poll_s: float = 0.1) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(poll_s)
    tails = "\n\n".join(p.read_text(errors="replace")[-3000:] for p in logs if p.exists())
    raise AssertionError(f"timed out waiting for {what}\n{tails}")


@pytest.mark.postgres
def test_frozen_worker_is_taken_over_and_its_late_results_discarded(tmp_path: Path, empty_pg_url: str) -> None:
    env = server_env(tmp_path, empty_pg_url)
    env["GAITMON_JOB_RUNNER"] = "procrastinate"
    env["GAITMON_JOB_STALL_SECONDS"] = str(STALL_S)
    subprocess.run(gaitmon_command() + ["migrate"], env=env, cwd=tmp_path, check=True, capture_output=True,
                   timeout=120)
    # A long session so that the frozen worker is caught mid-way.
    sid, _ = insert_simulated_session(empty_pg_url, n_strides=600, seed=8)
    defer_session(empty_pg_url, sid)
    close_api_apps()

    logs = [tmp_path / "worker_a.log", tmp_path / "worker_b.log"]
    procs: list[subprocess.Popen] = []
    try:
        with logs[0].open("wb") as log_a:
            a = subprocess.Popen(gaitmon_command() + ["worker"], env=env, cwd=tmp_path, stdout=log_a,
                                 stderr=subprocess.STDOUT)
        procs.append(a)
        _wait(lambda: _session(empty_pg_url, sid)[0] != "queued", 60, "worker A to claim", logs, poll_s=0.005)
        os.kill(a.pid, signal.SIGSTOP)
        status, worker_a, attempts, _ = _session(empty_pg_url, sid)
        # a 10-minute session takes the worker well over a second: the 5 ms poll catches it mid-way
        assert status == "processing", f"worker A finished before it could be frozen ({status})"
        assert f":{a.pid}:" in worker_a and attempts == 1

        time.sleep(STALL_S + 1.0)  # A's heartbeat is now older than the stall limit
        with logs[1].open("wb") as log_b:
            b = subprocess.Popen(gaitmon_command() + ["worker"], env=env, cwd=tmp_path, stdout=log_b,
                                 stderr=subprocess.STDOUT)
        procs.append(b)
        _wait(lambda: _session(empty_pg_url, sid)[0] == "done", 90, "worker B to finish the session", logs)
        status, worker_b, attempts, n_strides = _session(empty_pg_url, sid)
        assert f":{b.pid}:" in worker_b and attempts == 2 and n_strides > 500

        os.kill(a.pid, signal.SIGCONT)  # the frozen machine comes back and finishes its stale run
        _wait(lambda: "lost" in logs[0].read_text(errors="replace"), 90, "worker A to notice its lost claim", logs)
        assert _session(empty_pg_url, sid) == ("done", worker_b, 2, n_strides)
    finally:
        for p in procs:
            if p.poll() is None:
                os.kill(p.pid, signal.SIGCONT)
                p.terminate()
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(10)
