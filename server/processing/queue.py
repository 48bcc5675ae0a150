"""Hand a queued session to the configured runner.

The session row (status "queued") is the source of truth; the queue only says "look now". Embedded and manual
runners find queued sessions by polling, so enqueue just wakes them. With procrastinate a job is deferred to the
PostgreSQL queue, with a queueing lock per session so repeated enqueues do not pile up jobs.
"""

from __future__ import annotations

import logging
import threading

from server.config import Settings

log = logging.getLogger("gaitmon.jobs")

_wakers: set[threading.Event] = set()
_wakers_lock = threading.Lock()


def register_waker(event: threading.Event) -> None:
    """Wake this event whenever a session is enqueued (the embedded runner)."""
    with _wakers_lock:
        _wakers.add(event)


def unregister_waker(event: threading.Event) -> None:
    """Stop waking this event."""
    with _wakers_lock:
        _wakers.discard(event)


def wake() -> None:
    """Wake every registered runner."""
    with _wakers_lock:
        for event in _wakers:
            event.set()


def enqueue(settings: Settings, session_id: str) -> None:
    """Make the runner pick up ``session_id`` (already committed with status "queued")."""
    if settings.resolved_job_runner == "procrastinate":
        from server.processing.worker import defer_session

        defer_session(settings.resolved_database_url, session_id)
    else:
        wake()
    log.info("session %s enqueued (%s)", session_id, settings.resolved_job_runner)
