"""Engine, sessions and the declarative base every domain's models derive from."""

from __future__ import annotations

import uuid

from sqlalchemy import create_engine, event
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker


def new_id() -> str:
    """A new primary key: 32 hex digits of a random UUID."""
    return uuid.uuid4().hex


def storable_key(key: str) -> bool:
    """Whether a key from a URL can be looked up at all: PostgreSQL text refuses NUL, so such a key is simply not
    found (404) instead of failing the query."""
    return "\x00" not in key


class Base(DeclarativeBase):
    """Declarative base of every table (every change needs an Alembic migration in ``migrations/versions``)."""


def make_engine(url: str) -> Engine:
    """The engine for a database URL (SQLite: WAL, foreign keys and a busy timeout on every connection)."""
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_conn, _record) -> None:  # noqa: ANN001
            # WAL lets the API read while the embedded worker writes; FKs make ON DELETE CASCADE work.
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.execute("PRAGMA busy_timeout=30000")
            cur.close()

        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=10)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """Sessions whose objects stay readable after commit (responses are built after the commit)."""
    return sessionmaker(bind=engine, expire_on_commit=False)
