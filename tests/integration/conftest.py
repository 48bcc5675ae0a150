"""Fixtures of the real-server tests: a free port, the gaitmon command, an empty PostgreSQL database."""

from __future__ import annotations

import os
import socket
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import fresh_postgres_database

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def gaitmon_command() -> list[str]:
    """The installed console script when present (``pip install -e .``), else the same entry point via -m."""
    script = Path(sys.executable).with_name("gaitmon")
    return [str(script)] if script.exists() else [sys.executable, "-m", "server.cli"]


def server_env(tmp_path: Path, database_url: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GAITMON_")}
    env["GAITMON_DATA_DIR"] = str(tmp_path / "data")
    env["GAITMON_LOG_LEVEL"] = "INFO"
    if database_url:
        env["GAITMON_DATABASE_URL"] = database_url
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.fixture
def empty_pg_url() -> Iterator[str]:
    """A database of its own with nothing in it, so `gaitmon serve` migrates it from scratch."""
    with fresh_postgres_database("gaitmon_walk") as url:
        yield url


def insert_simulated_session(url: str, *, n_strides: int = 16, seed: int = 4) -> tuple[str, int]:
    """A completed (queued) session holding a simulated recording, as the upload endpoint leaves it.

    Returns the session id and the number of stored samples.
    """
    from datetime import UTC, datetime

    from pipeline.simulate import SimConfig, simulate_session
    from server.db import make_engine, make_sessionmaker
    from server.patients.models import Patient
    from server.sessions.models import Session
    from tests.support.seed import add_stream_batches

    sim = simulate_session(SimConfig(n_strides=n_strides, seed=seed))
    engine = make_engine(url)
    with make_sessionmaker(engine)() as db:
        patient = Patient(display_name="simulated")
        db.add(patient)
        db.flush()
        sess = Session(patient_id=patient.id, client_session_id=f"sim-{seed}", started_at=datetime.now(UTC),
                       activity="walking", status="queued", completed_at=datetime.now(UTC))
        db.add(sess)
        db.flush()
        add_stream_batches(db, sess.id, sim.streams, 8)
        db.commit()
        sid = sess.id
    engine.dispose()
    return sid, sum(len(s.t_s) for s in sim.streams)
