"""Hand a queued session to the configured runner.

The session row (status "queued") is the source of truth; the queue only says "look now". Embedded and manual
runners find queued sessions by polling, so enqueue just wakes them. With procrastinate a job is deferred to the
PostgreSQL queue, with a queueing lock per session so repeated enqueues do not pile up jobs.
"""

from __future__ import annotations

import logging
import threading

from sqlalchemy import text
from sqlalchemy.orm import Session as DbSession

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


def forget_sessions(db: DbSession, session_ids: list[str]) -> None:
    """Remove what the queue keeps about sessions being deleted, in the deleting transaction.

    Embedded and manual runners keep nothing but the session row. Procrastinate keeps a job row per deferral
    (failed ones for good) holding the session id in ``args`` and ``queueing_lock``: those rows are deleted with
    their events, except the job a worker is running right now, whose row procrastinate still has to finish; it
    is anonymised (the worker finds the session gone and stores nothing).
    """
    if not session_ids or db.get_bind().dialect.name != "postgresql":
        return
    if db.execute(text("SELECT to_regclass('procrastinate_jobs')")).scalar() is None:
        return
    from server.processing.worker import PROCESS_TASK

    mine = "task_name = :task AND args->>'session_id' = ANY(:ids)"
    params = {"task": PROCESS_TASK, "ids": list(session_ids)}
    # Delete first: a job fetched meanwhile is "doing" when the DELETE gets its row, and the UPDATE catches it.
    db.execute(text(f"DELETE FROM procrastinate_jobs WHERE {mine} AND status <> 'doing'"), params)
    db.execute(text(f"UPDATE procrastinate_jobs SET args = jsonb_build_object('session_id', ''), "
                    f"queueing_lock = NULL WHERE {mine}"), params)
