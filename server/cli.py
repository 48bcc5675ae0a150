"""The ``gaitmon`` command: serve, migrate, create-token, revoke-token, worker, simulate.

Progress and logs go to stderr; the only stdout output of ``create-token`` is the token (its last line), so
``TOKEN=$(gaitmon create-token --role admin)`` works.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import inspect
import logging
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from sqlalchemy import select, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError

from server.config import Settings, get_settings
from server.enums import Role
from server.ops.logs import setup_logging
from server.simulate_cli import register as register_simulate
from server.utc import utcnow

log = logging.getLogger("gaitmon.cli")

# Any fixed number: serialises concurrent `migrate`/`serve` start-ups of several replicas on one PostgreSQL.
MIGRATION_LOCK_ID = 727_011_001


def package_version() -> str:
    """The installed distribution's version (``gaitmon --version``)."""
    try:
        return importlib.metadata.version("gaitmon")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed)"


def safe_url(url: str) -> str:
    """The database URL without its password, for logs and messages."""
    return make_url(url).render_as_string(hide_password=True)


def migrate_database(settings: Settings) -> None:
    """Alembic to head, plus procrastinate's schema on PostgreSQL; safe to run again and from several replicas."""
    from server.migrate import upgrade_to_head

    url = settings.resolved_database_url
    if settings.is_sqlite:
        upgrade_to_head(url)
        log.info("database migrated to head (%s)", safe_url(url))
        backfill_trend_summaries(settings)
        return
    from server.db import make_engine
    from server.processing.worker import apply_schema

    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT pg_advisory_lock(:k)"), {"k": MIGRATION_LOCK_ID})
            conn.commit()
            try:
                upgrade_to_head(url)
                installed = apply_schema(url)
            finally:
                conn.execute(text("SELECT pg_advisory_unlock(:k)"), {"k": MIGRATION_LOCK_ID})
                conn.commit()
    finally:
        engine.dispose()
    log.info("database migrated to head%s (%s)", ", procrastinate schema installed" if installed else "",
             safe_url(url))
    backfill_trend_summaries(settings)


def backfill_trend_summaries(settings: Settings) -> None:
    """Sessions processed before the trend tables (or a newer summary format) existed get their summaries now."""
    from server.trends.summaries import backfill

    factory = _sessionmaker(settings)
    try:
        backfill(factory)
    finally:
        factory.kw["bind"].dispose()


def describe_database(settings: Settings) -> str:
    """The database a command uses, for stderr: the absolute SQLite path says which file a relative data dir hit."""
    url = settings.resolved_database_url
    if settings.is_sqlite:
        path = Path(make_url(url).database or "")
        state = "" if path.exists() else " (new file: no server has used it yet)"
        return f"{path}{state}"
    return safe_url(url)


def cmd_serve(args: argparse.Namespace, settings: Settings) -> int:
    """``gaitmon serve``: migrate unless disabled, then run the API with uvicorn."""
    import uvicorn

    from server.app import create_app
    from server.http_protocol import ProblemHttpProtocol

    host = args.host or settings.host
    port = args.port if args.port is not None else settings.port
    if settings.auto_migrate:
        migrate_database(settings)
    else:
        log.info("GAITMON_AUTO_MIGRATE=false: not migrating")
    app = create_app(settings)
    log.info("gaitmon %s serving on http://%s:%d (database %s, jobs %s)", package_version(), host, port,
             safe_url(settings.resolved_database_url), settings.resolved_job_runner)
    # log_config=None: uvicorn's loggers propagate to ours (request id, JSON format) instead of printing their own.
    uvicorn.run(app, host=host, port=port, log_level=settings.log_level.lower(), proxy_headers=True,
                log_config=None, http=ProblemHttpProtocol)
    return 0


def cmd_migrate(args: argparse.Namespace, settings: Settings) -> int:
    """``gaitmon migrate``: bring the schema and the job queue to the latest version."""
    migrate_database(settings)
    return 0


def _sessionmaker(settings: Settings):  # noqa: ANN202
    from server import metadata as _metadata  # noqa: F401 - the commands write rows whose keys span domains
    from server.db import make_engine, make_sessionmaker

    return make_sessionmaker(make_engine(settings.resolved_database_url))


def cmd_create_token(args: argparse.Namespace, settings: Settings) -> int:
    """``gaitmon create-token``: an admin token, or a clinician with its token (printed last)."""
    from server.auth.models import Token
    from server.auth.service import create_clinician, issue_token

    if args.role == Role.clinician and not args.name:
        print("error: --name is required for --role clinician", file=sys.stderr)
        return 2
    # Said before anything is written: run from another directory, a relative GAITMON_DATA_DIR means another file.
    print(f"database: {describe_database(settings)}", file=sys.stderr)
    if settings.auto_migrate:
        # The first command on a fresh machine is often this one, before `serve` ever ran.
        migrate_database(settings)
    with _sessionmaker(settings)() as db:
        if args.role == Role.clinician:
            clinician, token = create_clinician(db, args.name, email=args.email)
            db.commit()
            print(f"created clinician {clinician.id} ({clinician.name})", file=sys.stderr)
            digest = hashlib.sha256(token.encode()).hexdigest()
            token_id = db.scalars(select(Token.id).where(Token.token_hash == digest)).one()
        else:
            row, token = issue_token(db, role=Role.admin, name=args.name)
            db.commit()
            token_id = row.id
        print(f"created {args.role} token {token_id} (shown once; revoke with: gaitmon revoke-token {token_id})",
              file=sys.stderr)
    sys.stderr.flush()
    print(token, flush=True)
    return 0


def cmd_revoke_token(args: argparse.Namespace, settings: Settings) -> int:
    """``gaitmon revoke-token``: revoke a token by its id."""
    from server.auth.models import Token

    with _sessionmaker(settings)() as db:
        row = db.get(Token, args.token_id)
        if row is None:
            print(f"error: no token with id {args.token_id}", file=sys.stderr)
            return 1
        if row.revoked_at is None:
            row.revoked_at = utcnow()
            db.commit()
            print(f"token {row.id} revoked", file=sys.stderr)
        else:
            print(f"token {row.id} was already revoked", file=sys.stderr)
    return 0


def cmd_worker(args: argparse.Namespace, settings: Settings) -> int:
    """``gaitmon worker``: process queued sessions until stopped."""
    if settings.resolved_job_runner == "procrastinate":
        from server.processing.worker import run_worker, schema_present

        if not schema_present(settings.resolved_database_url):
            print("error: the job queue schema is missing; run `gaitmon migrate` first", file=sys.stderr)
            return 1
        run_worker(settings, concurrency=args.concurrency)
        return 0
    from server.processing.embedded import EmbeddedRunner, worker_name

    if args.concurrency != 1:
        log.warning("--concurrency is ignored with the %s runner (one session at a time)",
                    settings.resolved_job_runner)
    # Another process (the API's embedded thread) may be working too: only heartbeat-stale sessions are recovered.
    runner = EmbeddedRunner(_sessionmaker(settings), settings, recover_all_at_start=False,
                            name=worker_name("worker"))

    def _stop(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping after the current session", signum)
        runner.request_stop()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    log.info("worker polling %s for queued sessions", safe_url(settings.resolved_database_url))
    runner.run()
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``gaitmon`` command line with its subcommands."""
    parser = argparse.ArgumentParser(prog="gaitmon", description="Gait monitoring backend")
    parser.add_argument("--version", action="version", version=f"gaitmon {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("serve", help="run the HTTP API (migrates the database first unless "
                                     "GAITMON_AUTO_MIGRATE=false)")
    p.add_argument("--host", default=None, help="listen address (default: GAITMON_HOST, 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="listen port (default: GAITMON_PORT, 8000)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("migrate", help="bring the database schema (and the job queue schema) to the latest version")
    p.set_defaults(func=cmd_migrate)

    p = sub.add_parser("create-token", help="create an admin token, or a clinician with its token; "
                                            "prints the token as the last line")
    p.add_argument("--role", choices=[Role.admin.value, Role.clinician.value], required=True)
    p.add_argument("--name", default=None)
    p.add_argument("--email", default=None)
    p.set_defaults(func=cmd_create_token)

    p = sub.add_parser("revoke-token", help="revoke a token by its id")
    p.add_argument("token_id")
    p.set_defaults(func=cmd_revoke_token)

    p = sub.add_parser("worker", help="process queued sessions (PostgreSQL: procrastinate worker; "
                                      "SQLite: polling loop)")
    p.add_argument("--concurrency", type=int, default=1)
    p.set_defaults(func=cmd_worker)

    register_simulate(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``gaitmon`` command; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    settings = get_settings()
    setup_logging(settings.log_level, settings.log_format)
    func = args.func
    # simulate_cli's handlers may take (args) only; ours take (args, settings).
    try:
        code = func(args, settings) if len(inspect.signature(func).parameters) >= 2 else func(args)
    except OperationalError as exc:
        # An operator error (database down, wrong URL), not a bug: one line, no traceback.
        reason = str(exc.orig or exc).strip().splitlines()[0] if str(exc.orig or exc).strip() else type(exc).__name__
        print(f"error: cannot use the database {safe_url(settings.resolved_database_url)}: {reason}",
              file=sys.stderr)
        return 1
    return int(code or 0)


if __name__ == "__main__":
    raise SystemExit(main())
