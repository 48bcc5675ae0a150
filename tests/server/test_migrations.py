"""Migrations: empty database -> head equals the models (alembic check), and downgrade/upgrade round-trips."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, inspect

from server.metadata import all_metadata
from server.migrate import alembic_config, include_name, upgrade_to_head
from tests.conftest import fresh_postgres_database


@pytest.fixture(params=["sqlite", "postgres"])
def empty_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A database with no tables at all (not the shared, already migrated test database)."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'empty.sqlite'}"
        return
    with fresh_postgres_database("gaitmon_mig") as url:
        yield url


def _diff(url: str) -> list:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            ctx = MigrationContext.configure(conn, opts={"compare_type": True, "include_name": include_name})
            return compare_metadata(ctx, all_metadata())
    finally:
        engine.dispose()


def _tables(url: str) -> set[str]:
    engine = create_engine(url)
    try:
        return set(inspect(engine).get_table_names())
    finally:
        engine.dispose()


def _current(url: str) -> str | None:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()
    finally:
        engine.dispose()


def test_upgrade_from_empty_matches_models(empty_url: str) -> None:
    assert _tables(empty_url) == set()
    upgrade_to_head(empty_url)
    head = ScriptDirectory.from_config(alembic_config(empty_url)).get_current_head()
    assert _current(empty_url) == head
    assert set(all_metadata().tables) <= _tables(empty_url)
    # Like `alembic check`: a model change without a migration shows up here.
    assert _diff(empty_url) == []


def test_downgrade_to_base_and_up_again(empty_url: str) -> None:
    upgrade_to_head(empty_url)
    cfg = alembic_config(empty_url)
    command.downgrade(cfg, "base")
    assert _tables(empty_url) - {"alembic_version"} == set()
    assert _current(empty_url) is None
    command.upgrade(cfg, "head")
    assert _diff(empty_url) == []


def test_every_revision_steps_down_and_up(empty_url: str) -> None:
    """Each migration's downgrade undoes exactly its upgrade (checked one step at a time)."""
    cfg = alembic_config(empty_url)
    revisions = [r.revision for r in reversed(list(ScriptDirectory.from_config(cfg).walk_revisions()))]
    assert revisions[0] == "0001"
    for rev in revisions:
        command.upgrade(cfg, rev)
        tables_after_up = _tables(empty_url)
        command.downgrade(cfg, "-1")
        command.upgrade(cfg, rev)
        assert _tables(empty_url) == tables_after_up
        assert _current(empty_url) == rev


def test_gaitmon_migrate_is_idempotent_and_installs_the_queue(empty_url: str, tmp_path: Path) -> None:
    from server.cli import migrate_database
    from server.config import Settings

    settings = Settings(database_url=empty_url, data_dir=tmp_path / "data")
    migrate_database(settings)
    migrate_database(settings)  # a second run (another replica, a restart) changes nothing and does not fail
    tables = _tables(empty_url)
    if settings.is_sqlite:
        assert not any(t.startswith("procrastinate_") for t in tables)
    else:
        assert {"procrastinate_jobs", "procrastinate_workers"} <= tables
    # The queue's tables are not ours: the schema check still sees no difference.
    assert _diff(empty_url) == []


def test_0004_backfills_stride_activity_and_fallback_and_migrate_refills_trends(empty_url: str,
                                                                               tmp_path: Path) -> None:
    from sqlalchemy import text

    from server.cli import migrate_database
    from server.config import Settings

    cfg = alembic_config(empty_url)
    command.upgrade(cfg, "0003")
    engine = create_engine(empty_url)
    stride_cols = ("t_start_s, t_end_s, duration_s, t_toe_off_s, stance_time_s, swing_time_s, stance_pct, "
                   "peak_swing_flexion_deg, min_flexion_deg, rom_deg, stance_flexion_deg, quality")
    try:
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO patients (id, timezone, created_at) VALUES ('p1', 'UTC', :t)"),
                         {"t": "2026-11-01 00:00:00+00:00"})
            for sid, activity, estimators in (("run", "running", ["ekf"] * 6), ("walk", "walking",
                                                                                ["go"] * 4 + ["cf"] * 2)):
                conn.execute(text(
                    "INSERT INTO sessions (id, patient_id, client_session_id, started_at, activity, status, "
                    "created_at, attempts, processed_at) VALUES (:id, 'p1', :id, :t, :a, 'done', :t, 1, :t)"),
                    {"id": sid, "a": activity, "t": "2026-11-02 10:00:00+00:00"})
                for i, est in enumerate(estimators):
                    conn.execute(text(
                        f"INSERT INTO strides (session_id, patient_id, leg, \"index\", started_at, estimator, "
                        f"quality_reasons, {stride_cols}) VALUES (:sid, 'p1', 'left', :i, :t, :est, '[]', "
                        "1, 2.1, 1.1, 1.7, 0.66, 0.44, 60, 60, 2, 58, 15, 1)"),
                        {"sid": sid, "i": i, "est": est, "t": "2026-11-02 10:00:01+00:00"})
        migrate_database(Settings(database_url=empty_url, data_dir=tmp_path / "data"))
        with engine.connect() as conn:
            strides = conn.execute(text(
                "SELECT session_id, estimator, activity, fallback FROM strides ORDER BY session_id, \"index\""
            )).all()
            trends = conn.execute(text(
                "SELECT session_id, activity, n_strides, n_fallback FROM trend_session_legs ORDER BY session_id"
            )).all()
    finally:
        engine.dispose()
    assert [(s, e, a, bool(f)) for s, e, a, f in strides] == [
        ("run", "ekf", "running", False)] * 6 + [("walk", "go", "walking", False)] * 4 + [
        ("walk", "cf", "walking", True)] * 2
    # The running patient's strides are no fallback; the trends are rebuilt per activity.
    assert trends == [("run", "running", 6, 0), ("walk", "walking", 6, 2)]
    assert _diff(empty_url) == []
