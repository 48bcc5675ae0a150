"""The embedded runner never steals a live claim: a second `gaitmon serve` on the same database must leave a
session that another process is working on (fresh heartbeat) alone, and take up only stale or orphaned claims."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import pytest

from server.config import Settings
from server.processing import embedded
from server.processing import jobs as process
from server.processing.embedded import claim_of_dead_local_process, worker_name
from tests.server.test_jobs import data_processor, get, make_session, sm  # noqa: F401 - the sm fixture


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def wait_for(predicate, timeout_s: float = 20.0) -> bool:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def test_claim_tokens_of_dead_local_processes_are_recognised() -> None:
    host = socket.gethostname()
    assert claim_of_dead_local_process(f"embedded@{host}:{dead_pid()}:abc123")
    assert not claim_of_dead_local_process(f"{worker_name('embedded')}-other:abc")  # unparseable: assume alive
    parent = os.getppid()  # alive, not this process
    assert not claim_of_dead_local_process(f"embedded@{host}:{parent}:abc123")
    assert not claim_of_dead_local_process(f"embedded@another-host:{dead_pid()}:abc123")
    assert not claim_of_dead_local_process("inline:abc123")


def test_a_starting_runner_leaves_live_claims_and_takes_orphans(settings: Settings, sm,  # noqa: ANN001, F811
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(process, "_default_processor", data_processor())
    live_elsewhere = make_session(sm, seed=1)
    live_here = make_session(sm, seed=2)
    orphan = make_session(sm, seed=3)
    # Another machine's worker, and another live API process on this machine, both heart-beating.
    assert process.claim(sm, live_elsewhere, "embedded@other-host:4242")
    assert process.claim(sm, live_here, f"embedded@{socket.gethostname()}:{os.getppid()}")
    # A killed API process of this machine.
    assert process.claim(sm, orphan, f"embedded@{socket.gethostname()}:{dead_pid()}")
    runner = embedded.start(sm, settings)  # what the API process runs at start-up
    try:
        assert wait_for(lambda: get(sm, orphan).status == "done")
        time.sleep(0.5)  # several polls later the live ones are still theirs
        for sid in (live_elsewhere, live_here):
            row = get(sm, sid)
            assert row.status == "processing" and row.attempts == 1, (sid, row.status)
    finally:
        runner.stop()
