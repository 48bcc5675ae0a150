"""Migration 0005 (knee calibrations) up and down on SQLite and PostgreSQL, with data around it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from alembic import command
from sqlalchemy import create_engine, inspect, text

from server.migrate import alembic_config
from tests.conftest import fresh_postgres_database


@pytest.fixture(params=["sqlite", "postgres"])
def empty_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A database with no tables at all."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'empty.sqlite'}"
        return
    with fresh_postgres_database("gaitmon_mig_cal") as url:
        yield url


def test_0005_adds_and_removes_only_the_calibration_table(empty_url: str) -> None:
    cfg = alembic_config(empty_url)
    command.upgrade(cfg, "0004")
    engine = create_engine(empty_url)
    try:
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO patients (id, timezone, created_at) VALUES ('p1', 'UTC', :t)"),
                         {"t": "2026-11-01 00:00:00+00:00"})
        before = set(inspect(engine).get_table_names())
        assert "knee_calibrations" not in before

        command.upgrade(cfg, "0005")
        insp = inspect(engine)
        assert set(insp.get_table_names()) == before | {"knee_calibrations"}
        assert [ix["column_names"] for ix in insp.get_indexes("knee_calibrations")] == [
            ["patient_id", "leg", "measured_at"]]
        assert [fk["referred_table"] for fk in insp.get_foreign_keys("knee_calibrations")] == ["patients"]
        with engine.begin() as conn:
            conn.execute(text(
                "INSERT INTO knee_calibrations (id, patient_id, leg, standing_knee_deg, measured_at, method, "
                "created_at) VALUES ('c1', 'p1', 'left', 9.5, :t, 'goniometer', :t)"), {"t": "2026-11-02 08:00:00"})
        with engine.connect() as conn:
            assert conn.execute(text("SELECT standing_knee_deg FROM knee_calibrations")).scalar_one() == 9.5

        command.downgrade(cfg, "0004")
        assert set(inspect(engine).get_table_names()) == before
        with engine.connect() as conn:
            assert conn.execute(text("SELECT id FROM patients")).scalars().all() == ["p1"]
        command.upgrade(cfg, "0005")
        with engine.connect() as conn:
            assert conn.execute(text("SELECT count(*) FROM knee_calibrations")).scalar_one() == 0
    finally:
        engine.dispose()
