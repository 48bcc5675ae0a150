"""The `gaitmon` command's job and token subcommands, run as real subprocesses on an SQLite file."""

from __future__ import annotations

import hashlib
import signal
import subprocess
import time
from pathlib import Path

import pytest
from sqlalchemy import select

from server import cli
from server.auth.models import Clinician, Token
from server.config import Settings
from server.db import make_engine, make_sessionmaker
from server.results.models import Stride
from server.sessions.models import Session
from tests.integration.conftest import gaitmon_command, insert_simulated_session, server_env


def run(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(gaitmon_command() + args, env=env, cwd=cwd, capture_output=True, text=True, timeout=120)


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    return server_env(tmp_path, None)


def db_url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'data' / 'gaitmon.sqlite'}"


def test_tokens_from_the_command_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    # In-process (the real-server walk runs these as subprocesses); the settings are the ones of a fresh machine.
    settings = Settings(data_dir=tmp_path / "data")
    monkeypatch.setattr(cli, "get_settings", lambda: settings)
    # main() points the root logger at the stderr of the moment; under pytest that is a capture file closed later.
    monkeypatch.setattr(cli, "setup_logging", lambda level, fmt="text": None)
    assert cli.main(["create-token", "--role", "clinician", "--name", "Dr Who", "--email", "who@example.org"]) == 0
    out, err = capsys.readouterr()
    token = out.strip().splitlines()[-1]
    sm = make_sessionmaker(make_engine(db_url(tmp_path)))  # create-token migrated the fresh database itself
    with sm() as db:
        row = db.scalars(select(Token).where(Token.token_hash == hashlib.sha256(token.encode()).hexdigest())).one()
        assert row.role == "clinician" and row.clinician_id and row.revoked_at is None
        assert db.get(Clinician, row.clinician_id).email == "who@example.org"
        token_id = row.id
    assert token not in err and token_id in err  # the secret on stdout only; the id to revoke it on stderr
    assert cli.main(["revoke-token", token_id]) == 0
    with sm() as db:
        assert db.get(Token, token_id).revoked_at is not None
    assert cli.main(["revoke-token", "0" * 32]) == 1
    assert cli.main(["create-token", "--role", "clinician"]) == 2  # needs --name
    assert cli.main(["create-token", "--role", "admin"]) == 0
    with sm() as db:
        assert db.scalars(select(Token.role).order_by(Token.created_at)).all() == ["clinician", "admin"]
    sm.kw["bind"].dispose()


def test_sqlite_worker_processes_queue_and_stops_on_sigterm(tmp_path: Path, env: dict[str, str]) -> None:
    assert run(["migrate"], env, tmp_path).returncode == 0
    sid, _ = insert_simulated_session(db_url(tmp_path))
    log_path = tmp_path / "worker.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(gaitmon_command() + ["worker"], env=env, cwd=tmp_path, stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            sm = make_sessionmaker(make_engine(db_url(tmp_path)))
            deadline = time.monotonic() + 90
            status = "queued"
            while time.monotonic() < deadline and status in ("queued", "processing"):
                time.sleep(0.2)
                with sm() as db:
                    status = db.get(Session, sid).status
            assert status == "done", log_path.read_text()
            with sm() as db:
                assert db.scalars(select(Stride).where(Stride.session_id == sid)).first() is not None
                assert db.get(Session, sid).worker_id.startswith("worker@")
            sm.kw["bind"].dispose()
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(30) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert "stopping after the current session" in log_path.read_text()
