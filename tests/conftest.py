"""Shared fixtures: every HTTP test runs on SQLite and on a real PostgreSQL.

PostgreSQL comes from GAITMON_TEST_POSTGRES_URL (default: the local trust-auth server, database ``test``). Each
pytest-xdist worker gets a database of its own, created from that URL. Without a reachable server the PostgreSQL
variants skip with the reason, unless GAITMON_REQUIRE_POSTGRES=1 (set by .ci/run), which turns the skip into a
failure.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from server.config import Settings
from server.migrate import upgrade_to_head

PG_URL = os.environ.get("GAITMON_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
REQUIRE_PG = os.environ.get("GAITMON_REQUIRE_POSTGRES") == "1"
REQUIRE_REAL_DATA = os.environ.get("GAITMON_REQUIRE_REAL_DATA") == "1"


def skip_without_real_data(available: bool, what: str) -> None:
    """Skip when a shared real recording is absent; fail instead under GAITMON_REQUIRE_REAL_DATA=1 (CI)."""
    if available:
        return
    reason = f"real data folder ../shared/data/real ({what}) is absent"
    if REQUIRE_REAL_DATA:
        pytest.fail(reason + " (GAITMON_REQUIRE_REAL_DATA=1)")
    pytest.skip(reason)


def _worker_suffix() -> str:
    # the pid keeps concurrent pytest runs on one machine out of each other's databases
    return f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}_{os.getpid()}"


@contextmanager
def fresh_postgres_database(prefix: str) -> Iterator[str]:
    """A new, empty PostgreSQL database named for this test process, dropped afterwards.

    Skips (or fails under GAITMON_REQUIRE_POSTGRES=1) when the server is not reachable.
    """
    admin = create_engine(PG_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            conn.execute(text("select 1"))
    except Exception as exc:  # noqa: BLE001 - any connection failure means "not reachable"
        admin.dispose()
        reason = f"PostgreSQL not reachable at {PG_URL}: {type(exc).__name__}"
        if REQUIRE_PG:
            pytest.fail(reason + " (GAITMON_REQUIRE_POSTGRES=1)")
        pytest.skip(reason)
    name = f"{prefix}_{_worker_suffix()}"
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield make_url(PG_URL).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    """A freshly created, migrated PostgreSQL database for this test worker."""
    with fresh_postgres_database("gaitmon_test") as url:
        upgrade_to_head(url)
        yield url


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One migrated SQLite file, copied for each test (faster than migrating every time)."""
    path = tmp_path_factory.mktemp("sqlite-template") / "template.sqlite"
    upgrade_to_head(f"sqlite:///{path}")
    return path


def _truncate_all(url: str) -> None:
    engine = create_engine(url)
    with engine.begin() as conn:
        tables = conn.execute(text(
            "select tablename from pg_tables where schemaname = 'public' and tablename <> 'alembic_version'"
        )).scalars().all()
        if tables:
            conn.execute(text("TRUNCATE " + ", ".join(f'"{t}"' for t in tables) + " RESTART IDENTITY CASCADE"))
    engine.dispose()


@pytest.fixture(params=["sqlite", "postgres"])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """An empty, migrated database: SQLite file or the worker's PostgreSQL database (truncated)."""
    if request.param == "sqlite":
        path = tmp_path / "gaitmon.sqlite"
        shutil.copy(request.getfixturevalue("sqlite_template"), path)
        return f"sqlite:///{path}"
    url = request.getfixturevalue("postgres_url")
    _truncate_all(url)
    return url


@pytest.fixture
def settings(database_url: str, tmp_path: Path) -> Settings:
    # job_runner "manual": tests drive the queue themselves (see server.processing) unless a test asks otherwise.
    return Settings(database_url=database_url, data_dir=tmp_path / "data", job_runner="manual")
