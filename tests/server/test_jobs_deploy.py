"""The production compose file and Dockerfile say what the design says (no Docker engine needed to check this)."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from server.cli import build_parser
from server.config import Settings

ROOT = Path(__file__).resolve().parents[2]


def _compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _gaitmon_command(service: dict) -> list[str]:
    cmd = service["command"]
    assert isinstance(cmd, list) and cmd[0] == "gaitmon"
    return cmd[1:]


def test_compose_services_and_dependencies() -> None:
    services = _compose()["services"]
    assert set(services) == {"db", "migrate", "api", "worker"}
    db = services["db"]
    assert db["image"] == "postgres:16"
    assert "pg_isready" in " ".join(db["healthcheck"]["test"])
    assert services["migrate"]["restart"] == "no"
    for name in ("api", "worker"):
        deps = services[name]["depends_on"]
        assert deps["db"]["condition"] == "service_healthy"
        assert deps["migrate"]["condition"] == "service_completed_successfully"
    assert services["worker"]["deploy"]["replicas"] == 2
    assert "/healthz" in " ".join(services["api"]["healthcheck"]["test"])


def test_compose_commands_parse_with_the_real_cli() -> None:
    services = _compose()["services"]
    parser = build_parser()
    api = parser.parse_args(_gaitmon_command(services["api"]))
    assert (api.command, api.host, api.port) == ("serve", "0.0.0.0", 8000)
    assert services["api"]["ports"] == [f"{api.port}:{api.port}"]
    assert parser.parse_args(_gaitmon_command(services["worker"])).command == "worker"
    assert parser.parse_args(_gaitmon_command(services["migrate"])).command == "migrate"


def test_compose_environment_is_understood_by_the_settings() -> None:
    services = _compose()["services"]
    known = {f"GAITMON_{name.upper()}" for name in Settings.model_fields} | {"GAITMON_AUTO_MIGRATE"}
    for name in ("migrate", "api", "worker"):
        env = services[name]["environment"]
        assert set(env) <= known, set(env) - known
        assert env["GAITMON_JOB_RUNNER"] == "procrastinate"
        url = env["GAITMON_DATABASE_URL"].replace("${POSTGRES_PASSWORD:-gaitmon}", "pw")
        # Same credentials and database as the db service declares.
        db_env = services["db"]["environment"]
        assert url == f"postgresql+psycopg://{db_env['POSTGRES_USER']}:pw@db:5432/{db_env['POSTGRES_DB']}"
        values = {k.removeprefix("GAITMON_").lower(): v for k, v in env.items()
                  if k != "GAITMON_AUTO_MIGRATE" and "${" not in v}
        settings = Settings(**values, database_url=url)
        assert settings.resolved_job_runner == "procrastinate" and not settings.is_sqlite
    assert services["api"]["environment"]["GAITMON_AUTO_MIGRATE"] == "false"


def test_dockerfile_installs_the_package_and_serves() -> None:
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim$", text, re.M)
    assert "pip install --no-deps ." in text
    copied = set(re.findall(r"^COPY (\S+) ", text, re.M))
    # Every package pyproject ships must be in the image.
    for pkg in ("pipeline", "server", "migrations"):
        assert pkg in copied and (ROOT / pkg).is_dir()
    assert re.search(r'^CMD \["gaitmon", "serve", "--host", "0\.0\.0\.0"', text, re.M)
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ".venv" in ignored and ".git" in ignored
