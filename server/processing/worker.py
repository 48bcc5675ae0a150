"""The PostgreSQL job queue: a procrastinate app, its tasks, and the worker of ``gaitmon worker``.

Why procrastinate: the queue lives in the PostgreSQL database the service already needs (no broker to run),
jobs are deferred by ``INSERT`` and fetched with ``SELECT ... FOR UPDATE SKIP LOCKED``, workers are woken by
LISTEN/NOTIFY and heart-beat in ``procrastinate_workers``, so any number of workers on any number of machines
share one queue.

Guarantees, layer by layer:
- ``queueing_lock=<session id>``: at most one waiting job per session (a second enqueue while one waits is a
  no-op), so "complete" followed by "reprocess" does not pile up jobs.
- no procrastinate ``lock``: the claim below already excludes concurrent processing, and a lock would be held by
  the "doing" job of a crashed worker until procrastinate declares that worker dead, delaying the recovery.
- the atomic claim in :mod:`server.processing.jobs` (``status='queued'`` -> ``'processing'``): whatever the queue
  does (a job delivered again after a worker was presumed dead, a job deferred twice), only one runner processes
  a given queued session, and only the holder of the claim may store results.
- recovery (periodic task ``gaitmon.recover`` every minute and at worker start): procrastinate jobs of workers
  that stopped heart-beating are marked failed (they would stay "doing" forever); sessions whose own heartbeat
  is older than ``job_stall_seconds`` go back to "queued" and get a new job.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import logging
import threading
from functools import lru_cache

import procrastinate
from procrastinate import exceptions as pexc
from procrastinate.jobs import Status
from sqlalchemy import text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.config import Settings, get_settings
from server.db import make_engine, make_sessionmaker
from server.processing import jobs
from server.processing.embedded import worker_name

log = logging.getLogger("gaitmon.jobs")

QUEUE = "gaitmon"
PROCESS_TASK = "gaitmon.process_session"
RECOVER_TASK = "gaitmon.recover"
# Procrastinate's own worker liveness: a worker silent this long is considered dead and its jobs are freed.
WORKER_HEARTBEAT_S = 10.0
WORKER_STALLED_S = 60.0


def conninfo(database_url: str) -> str:
    """libpq connection string from an SQLAlchemy URL (``postgresql+psycopg://`` -> ``postgresql://``)."""
    return make_url(database_url).set(drivername="postgresql").render_as_string(hide_password=False)


@lru_cache(maxsize=8)
def _sessionmaker(database_url: str) -> sessionmaker[DbSession]:
    # One engine per worker process (tasks run in threads of the worker's event loop).
    return make_sessionmaker(make_engine(database_url))


def make_app(database_url: str, settings: Settings | None = None, **pool_kwargs: object) -> procrastinate.App:
    """A procrastinate app bound to ``database_url`` with the gaitmon tasks registered."""
    settings = settings or get_settings()
    app = procrastinate.App(connector=procrastinate.PsycopgConnector(conninfo=conninfo(database_url),
                                                                     **pool_kwargs))

    @app.task(name=PROCESS_TASK, queue=QUEUE, pass_context=True)
    def process_session_task(context: procrastinate.JobContext, session_id: str) -> str:
        name = (context.additional_context or {}).get("worker_name") or worker_name("procrastinate")
        heartbeat_s = max(0.5, min(jobs.DEFAULT_HEARTBEAT_S, settings.job_stall_seconds / 4))
        outcome = jobs.process_one(_sessionmaker(database_url), session_id, worker_id=name,
                                      heartbeat_s=heartbeat_s)
        log.info("job %s: session %s %s", context.job.id if context.job else "?", session_id, outcome)
        return outcome

    @app.periodic(cron="* * * * *", periodic_id="recover")
    @app.task(name=RECOVER_TASK, queue=QUEUE, queueing_lock=RECOVER_TASK, pass_context=False)
    async def recover_task(timestamp: int) -> int:
        return await recover_async(app, database_url, settings)

    return app


async def recover_async(app: procrastinate.App, database_url: str, settings: Settings) -> int:
    """Free jobs of dead procrastinate workers, re-queue stalled sessions and defer their jobs again."""
    for job in await app.job_manager.get_stalled_jobs(queue=QUEUE, seconds_since_heartbeat=WORKER_STALLED_S):
        log.warning("procrastinate job %s (%s) of a dead worker marked failed", job.id, job.task_name)
        await app.job_manager.finish_job(job, status=Status.FAILED, delete_job=False)
    ids = await asyncio.to_thread(jobs.recover_stalled, _sessionmaker(database_url),
                                  stall_seconds=settings.job_stall_seconds)
    # Also sessions that are queued but have no waiting job (e.g. the API crashed between commit and defer).
    ids += await asyncio.to_thread(_queued_without_job, database_url)
    unique = list(dict.fromkeys(ids))
    for sid in unique:
        await _defer_async(app, sid)
    if unique:
        log.warning("recovery: %d session(s) deferred again", len(unique))
    return len(unique)


def _queued_without_job(database_url: str) -> list[str]:
    with _sessionmaker(database_url)() as db:
        return list(db.scalars(text(
            "SELECT s.id FROM sessions s WHERE s.status = 'queued' AND NOT EXISTS ("
            " SELECT 1 FROM procrastinate_jobs j WHERE j.queueing_lock = s.id AND j.status IN ('todo', 'doing'))"
        )).all())


async def _defer_async(app: procrastinate.App, session_id: str) -> None:
    # AlreadyEnqueued: a job for this session is already waiting; it will find the session queued.
    with contextlib.suppress(pexc.AlreadyEnqueued):
        await app.configure_task(PROCESS_TASK, queueing_lock=session_id).defer_async(session_id=session_id)


_api_apps: dict[str, procrastinate.App] = {}
_api_apps_lock = threading.Lock()


def _api_app(database_url: str) -> procrastinate.App:
    # The API process defers synchronously through a small pool opened on first use and kept for the process.
    with _api_apps_lock:
        app = _api_apps.get(database_url)
        if app is None:
            app = make_app(database_url, min_size=1, max_size=4).open()
            if not _api_apps:
                atexit.register(close_api_apps)
            _api_apps[database_url] = app
        return app


def defer_session(database_url: str, session_id: str) -> None:
    """Defer the processing job of a queued session (no-op when one is already waiting).

    Never raises: the session is already committed as "queued", and the workers' periodic recovery defers a job
    for any queued session that has none, so a failed defer only delays processing by up to a minute.
    """
    try:
        _api_app(database_url).configure_task(PROCESS_TASK, queueing_lock=session_id).defer(session_id=session_id)
    except pexc.AlreadyEnqueued:
        log.info("session %s already has a waiting job", session_id)
    except Exception:  # noqa: BLE001
        log.exception("session %s: deferring its job failed; the workers' recovery will pick it up", session_id)


def close_api_apps() -> None:
    """Close the procrastinate apps the API opened to defer jobs."""
    with _api_apps_lock:
        for app in _api_apps.values():
            app.close()
        _api_apps.clear()


def schema_present(database_url: str) -> bool:
    """Whether procrastinate's tables exist in this database."""
    with _sessionmaker(database_url)() as db:
        return db.execute(text("SELECT to_regclass('procrastinate_jobs')")).scalar() is not None


def apply_schema(database_url: str) -> bool:
    """Install procrastinate's tables and functions once; returns True when it was installed now."""
    if schema_present(database_url):
        return False
    app = make_app(database_url, min_size=1, max_size=1)
    with app.open():
        app.schema_manager.apply_schema()
    log.info("procrastinate schema installed")
    return True


def run_worker(settings: Settings, *, concurrency: int = 1, wait: bool = True, name: str | None = None,
               install_signal_handlers: bool = True) -> None:
    """Run a procrastinate worker on the gaitmon queue (``wait=False``: stop once the queue is empty)."""
    url = settings.resolved_database_url
    name = name or worker_name("worker")
    app = make_app(url, settings)

    async def main() -> None:
        async with app.open_async():
            await recover_async(app, url, settings)
            await app.run_worker_async(
                queues=[QUEUE], concurrency=concurrency, wait=wait, name=name,
                additional_context={"worker_name": name}, install_signal_handlers=install_signal_handlers,
                update_heartbeat_interval=WORKER_HEARTBEAT_S, stalled_worker_timeout=WORKER_STALLED_S,
                delete_jobs="successful",
            )

    log.info("procrastinate worker %s on queue %r, concurrency %d", name, QUEUE, concurrency)
    asyncio.run(main())
