"""The embedded runner: a thread that processes queued sessions (the SQLite default, no extra process).

It polls for status "queued" every ``poll_s`` seconds, is woken at once by :func:`server.processing.queue.enqueue`, and
periodically re-queues sessions whose worker stopped heart-beating. At start-up it never takes a live claim (a
second ``gaitmon serve`` or a ``gaitmon worker`` on the same database may be working): it re-queues claims whose
heartbeat is stale, and claims of a runner on this machine whose process is gone (a killed or restarted API
process), so a restart does not wait ``GAITMON_JOB_STALL_SECONDS`` for its own orphans.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time

from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.config import Settings
from server.processing import jobs, queue

log = logging.getLogger("gaitmon.jobs")

POLL_S = 0.5


def worker_name(prefix: str) -> str:
    """A name for a runner: prefix, host and process id."""
    return f"{prefix}@{socket.gethostname()}:{os.getpid()}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True


def claim_of_dead_local_process(token: str) -> bool:
    """True when a claim token (``<prefix>@<host>:<pid>:<nonce>``) was made by a process of this machine that no
    longer runs, or by an earlier process with this process's pid (a container restart reuses pid and hostname;
    a runner that has just started holds no claim yet)."""
    _, at, rest = token.partition("@")
    host, _, tail = rest.rpartition(":")  # tail: the nonce
    host, _, pid_text = host.rpartition(":")
    if not at or host != socket.gethostname() or not pid_text.isdigit():
        return False
    pid = int(pid_text)
    return pid == os.getpid() or not _pid_alive(pid)


class EmbeddedRunner:
    """The in-process job runner used with SQLite: one thread that processes queued sessions."""

    def __init__(self, sm: sessionmaker[DbSession], settings: Settings, *, recover_all_at_start: bool = False,
                 poll_s: float = POLL_S, name: str | None = None) -> None:
        self._sm = sm
        self._settings = settings
        self._recover_all_at_start = recover_all_at_start
        self._poll_s = poll_s
        self.name = name or worker_name("embedded")
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # Heartbeat well inside the stall limit so a slow but live job is never taken over.
        self._heartbeat_s = max(0.5, min(jobs.DEFAULT_HEARTBEAT_S, settings.job_stall_seconds / 4))
        self._recover_every_s = max(1.0, min(60.0, settings.job_stall_seconds / 2))

    def start(self) -> EmbeddedRunner:
        queue.register_waker(self._wake)
        self._thread = threading.Thread(target=self.run, name="gaitmon-embedded-runner", daemon=True)
        self._thread.start()
        log.info("embedded job runner started (%s)", self.name)
        return self

    def request_stop(self) -> None:
        """Ask the loop to end after the session in progress (safe from a signal handler)."""
        self._stop.set()
        self._wake.set()

    def stop(self, timeout: float = 30.0) -> None:
        """Stop after the session in progress (a session cut short stays "processing" and is recovered later)."""
        self.request_stop()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("embedded job runner still busy after %.0f s; leaving it to exit with the process",
                            timeout)
        queue.unregister_waker(self._wake)
        log.info("embedded job runner stopped")

    def run(self) -> None:
        """The loop; runs in the thread started by :meth:`start`, or in the foreground (``gaitmon worker``)."""
        self._recover(everything=self._recover_all_at_start, at_start=True)
        last_recover = time.monotonic()
        while not self._stop.is_set():
            try:
                jobs.run_queued(self._sm, worker_id=self.name, should_stop=self._stop.is_set,
                                   heartbeat_s=self._heartbeat_s)
                if time.monotonic() - last_recover >= self._recover_every_s:
                    self._recover(everything=False)
                    last_recover = time.monotonic()
            except Exception:  # noqa: BLE001 - e.g. database briefly away: keep the runner alive and retry
                log.exception("embedded job runner: loop error; retrying")
            self._wake.wait(self._poll_s)
            self._wake.clear()

    def _recover(self, *, everything: bool, at_start: bool = False) -> None:
        try:
            ids = jobs.recover_stalled(self._sm, stall_seconds=self._settings.job_stall_seconds,
                                       everything=everything,
                                       orphaned=claim_of_dead_local_process if at_start else None)
        except Exception:  # noqa: BLE001
            log.exception("embedded job runner: stall recovery failed")
            return
        if ids:
            log.warning("re-queued %d stalled session(s): %s", len(ids), ", ".join(ids))


def start(sm: sessionmaker[DbSession], settings: Settings) -> EmbeddedRunner:
    """Start the runner thread of the API process; call ``.stop()`` on shutdown."""
    return EmbeddedRunner(sm, settings).start()
