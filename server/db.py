"""Engine, sessions and the declarative base every domain's models derive from."""

from __future__ import annotations

import uuid
from typing import TYPE_CHECKING

from sqlalchemy import create_engine, event
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker

if TYPE_CHECKING:
    from server.config import Settings

# Seconds to wait for the TCP connection to PostgreSQL: an unreachable database answers 503 quickly.
CONNECT_TIMEOUT_S = 5


def new_id() -> str:
    """A new primary key: 32 hex digits of a random UUID."""
    return uuid.uuid4().hex


def storable_key(key: str) -> bool:
    """Whether a key from a URL can be looked up at all: PostgreSQL text refuses NUL, so such a key is simply not
    found (404) instead of failing the query."""
    return "\x00" not in key


class Base(DeclarativeBase):
    """Declarative base of every table (every change needs an Alembic migration in ``migrations/versions``)."""


def make_engine(url: str, settings: Settings | None = None) -> Engine:
    """The engine for a database URL, its pool sized from ``settings`` (``GAITMON_DB_POOL_*``).

    SQLite: WAL, foreign keys and a busy timeout on every connection. A pool that cannot hand out a connection
    within ``db_pool_timeout_s`` raises :class:`sqlalchemy.exc.TimeoutError`, answered 503 by
    :mod:`server.errors`.
    """
    from server.config import Settings

    settings = settings or Settings()
    pool = {"pool_size": settings.db_pool_size, "max_overflow": settings.db_max_overflow,
            "pool_timeout": settings.db_pool_timeout_s}
    if url.startswith("sqlite"):
        busy_ms = int(settings.sqlite_busy_timeout_s * 1000)
        if ":memory:" in url or url in ("sqlite://", "sqlite:///"):
            pool = {}  # a memory database lives in one connection (SingletonThreadPool)
        engine = create_engine(url, connect_args={"check_same_thread": False,
                                                  "timeout": settings.sqlite_busy_timeout_s}, **pool)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record) -> None:  # noqa: ANN001
            # WAL lets the API read while the embedded worker writes; FKs make ON DELETE CASCADE work.
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute(f"PRAGMA busy_timeout={busy_ms}")
            cur.close()

        return engine
    return create_engine(url, pool_pre_ping=True, connect_args={"connect_timeout": CONNECT_TIMEOUT_S}, **pool)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """Sessions whose objects stay readable after commit (responses are built after the commit)."""
    return sessionmaker(bind=engine, expire_on_commit=False)


def make_upload_engine(url: str, settings: Settings) -> Engine | None:
    """PostgreSQL: the engine of the batch upload's single statement, ``None`` elsewhere (SQLite shares one).

    Its connections are in autocommit from the start, so a checkout neither switches the isolation level nor
    resets it on return, and it has no pre-ping: the three round trips around each INSERT were a third of the
    upload's database work. A connection found dead by its statement invalidates the pool and the upload retries
    once (:meth:`server.sessions.group_commit.GroupCommitter._alone`; the INSERT is idempotent). One connection
    per upload thread.
    """
    if url.startswith("sqlite"):
        return None
    size = settings.upload_thread_count
    return create_engine(url, isolation_level="AUTOCOMMIT", pool_pre_ping=False, pool_reset_on_return=None,
                         pool_size=size, max_overflow=0, pool_timeout=settings.db_pool_timeout_s,
                         connect_args={"connect_timeout": CONNECT_TIMEOUT_S})
