"""Engine, sessions and the metadata of every model module (for Alembic and the schema check)."""

from __future__ import annotations

from collections.abc import Iterator

from fastapi import Request
from sqlalchemy import MetaData, create_engine, event
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker


def make_engine(url: str) -> Engine:
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
    return sessionmaker(bind=engine, expire_on_commit=False)


def get_db(request: Request) -> Iterator[Session]:
    """FastAPI dependency: one ORM session per request, from the app's sessionmaker."""
    with request.app.state.sessionmaker() as db:
        yield db


def all_metadata() -> MetaData:
    """The metadata with every model module imported (add new model modules here)."""
    from server import models
    from server.trends import models as _trend_models  # noqa: F401 - registers the trend summary tables

    return models.Base.metadata
