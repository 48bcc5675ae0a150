"""Operations around the API: rate limits, CORS, request ids, JSON logs, settings from .env, create-token."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from limits import parse_many

from server import cli
from server.config import Settings
from server.ops.logs import setup_logging
from server.ops.request_id import request_id_var
from tests.server.helpers import Api, batch_body, bearer, open_api

PROBLEM = "application/problem+json"


@contextmanager
def api_with(tmp_path: Path, sqlite_template: Path, **overrides: Any) -> Iterator[Api]:
    path = tmp_path / "gaitmon.sqlite"
    shutil.copy(sqlite_template, path)
    settings = Settings(database_url=f"sqlite:///{path}", data_dir=tmp_path / "data", job_runner="manual",
                        **overrides)
    with open_api(settings) as api:
        yield api


def assert_429(resp: Any) -> dict[str, Any]:  # noqa: ANN401
    assert resp.status_code == 429, resp.text
    assert resp.headers["content-type"].startswith(PROBLEM)
    assert int(resp.headers["retry-after"]) >= 1
    body = resp.json()
    assert body["status"] == 429 and body["type"] == "urn:gaitmon:problem:rate-limited"
    return body


# memory:// counts through limits' synchronous API, any other storage through its async one: the same answers.
@pytest.mark.parametrize("storage", ["memory://", "async+memory://"])
def test_per_token_limit_answers_429_and_spares_other_tokens(tmp_path: Path, sqlite_template: Path,
                                                             storage: str) -> None:
    with api_with(tmp_path, sqlite_template, rate_limit_per_token="5/minute", rate_limit_storage=storage) as api:
        _, clin = api.clinician()
        _, other = api.clinician("Dr. Other")
        codes = [api.client.get("/v1/me", headers=bearer(clin)).status_code for _ in range(5)]
        assert codes == [200] * 5
        body = assert_429(api.client.get("/v1/me", headers=bearer(clin)))
        assert "retry after" in body["detail"]
        assert api.client.get("/v1/me", headers=bearer(other)).status_code == 200
        assert api.client.get("/healthz").status_code == 200  # probes are never limited


def test_per_ip_limit(tmp_path: Path, sqlite_template: Path) -> None:
    with api_with(tmp_path, sqlite_template, rate_limit_per_ip="8/minute", rate_limit_per_token="") as api:
        _, clin = api.clinician()
        _, other = api.clinician("Dr. Other")
        for i in range(6):  # two requests of the fixture (creating the clinicians) counted already
            assert api.client.get("/v1/me", headers=bearer(clin if i % 2 else other)).status_code == 200, i
        assert_429(api.client.get("/v1/me", headers=bearer(other)))


@pytest.mark.parametrize("storage", ["memory://", "async+memory://"])
def test_repeated_bad_tokens_are_slowed_but_working_tokens_are_not(tmp_path: Path, sqlite_template: Path,
                                                                   storage: str) -> None:
    with api_with(tmp_path, sqlite_template, rate_limit_storage=storage) as api:
        _, clin = api.clinician()
        assert api.client.get("/v1/me", headers=bearer(clin)).status_code == 200
        codes = [api.client.get("/v1/me", headers=bearer(f"gm_guess{i}")).status_code for i in range(40)]
        assert codes[:20] == [401] * 20  # the default budget: 20 failures a minute per address
        assert set(codes[20:]) == {429}
        assert_429(api.client.get("/v1/patients"))  # no token at all: also slowed
        # The clinician behind the same address keeps working.
        assert api.client.get("/v1/me", headers=bearer(clin)).status_code == 200


def test_default_limits_never_stop_a_phone_uploading_four_sensors(tmp_path: Path, sqlite_template: Path) -> None:
    # 4 sensors x 1 batch/s, plus a status poll every 5 s: what one device token sends at most in normal use.
    phone_per_s = 4 + 0.2
    for item in parse_many(Settings().rate_limit_per_token):
        seconds = item.get_expiry()
        assert item.amount >= 4 * phone_per_s * seconds, item  # at least 4x headroom in every window
    with api_with(tmp_path, sqlite_template) as api:
        _, dev, sess = api.setup_device_session()
        # Catching up after a dropped connection: 15 s of batches of both sensors sent back to back.
        codes = [api.upload(dev, sess["id"], batch_body(s, q)).status_code for q in range(15)
                 for s in ("L-thigh", "L-shank")]
        assert codes == [201] * 30


def test_cors_is_off_by_default(tmp_path: Path, sqlite_template: Path) -> None:
    with api_with(tmp_path, sqlite_template) as api:
        pre = api.client.options("/v1/sessions", headers={"Origin": "https://app.example",
                                                          "Access-Control-Request-Method": "POST"})
        assert pre.status_code == 405 and "access-control-allow-origin" not in pre.headers


def test_cors_preflight_and_response_headers_for_listed_origins(tmp_path: Path, sqlite_template: Path) -> None:
    with api_with(tmp_path, sqlite_template, cors_origins="https://app.example, https://other.example/") as api:
        _, clin = api.clinician()
        pre = api.client.options("/v1/sessions", headers={
            "Origin": "https://app.example", "Access-Control-Request-Method": "POST",
            "Access-Control-Request-Headers": "authorization, content-type, content-encoding"})
        assert pre.status_code == 200
        assert pre.headers["access-control-allow-origin"] == "https://app.example"
        assert "authorization" in pre.headers["access-control-allow-headers"].lower()
        got = api.client.get("/v1/me", headers={**bearer(clin), "Origin": "https://other.example"})
        assert got.status_code == 200 and got.headers["access-control-allow-origin"] == "https://other.example"
        assert "x-request-id" in got.headers["access-control-expose-headers"].lower()
        denied = api.client.options("/v1/sessions", headers={"Origin": "https://evil.example",
                                                             "Access-Control-Request-Method": "POST"})
        assert denied.status_code == 400 and "access-control-allow-origin" not in denied.headers


def test_request_id_is_honoured_when_sane(tmp_path: Path, sqlite_template: Path) -> None:
    with api_with(tmp_path, sqlite_template) as api:
        assert api.client.get("/healthz", headers={"X-Request-ID": "lb-42:a.b"}).headers["x-request-id"] == "lb-42:a.b"
        for bad in ("has space", "x" * 129, "semi;colon"):
            rid = api.client.get("/healthz", headers={"X-Request-ID": bad}).headers["x-request-id"]
            assert rid != bad and len(rid) == 32
        # Error answers carry one too (here a 404 problem document).
        assert len(api.client.get("/nope").headers["x-request-id"]) == 32


def test_json_logs_carry_the_request_id(capsys: pytest.CaptureFixture[str]) -> None:
    root = logging.getLogger()
    saved = (root.handlers[:], root.level)
    try:
        setup_logging("INFO", "json")
        token = request_id_var.set("req-7")
        try:
            logging.getLogger("gaitmon.test").info("hello %s", "world")
        finally:
            request_id_var.reset(token)
        logging.getLogger("gaitmon.test").warning("outside")
    finally:
        root.handlers[:], _ = saved
        root.setLevel(saved[1])
    lines = [json.loads(x) for x in capsys.readouterr().err.strip().splitlines()]
    assert lines[0]["message"] == "hello world" and lines[0]["request_id"] == "req-7"
    assert lines[0]["level"] == "INFO" and lines[0]["logger"] == "gaitmon.test" and "time" in lines[0]
    assert lines[1]["request_id"] == "-"


def test_every_setting_is_read_from_dot_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for key in ("GAITMON_AUTO_MIGRATE", "GAITMON_PORT", "GAITMON_HOST", "GAITMON_LOG_FORMAT", "GAITMON_CORS_ORIGINS"):
        monkeypatch.delenv(key, raising=False)
    (tmp_path / ".env").write_text("GAITMON_AUTO_MIGRATE=false\nGAITMON_PORT=9123\nGAITMON_HOST=0.0.0.0\n"
                                   "GAITMON_LOG_FORMAT=json\nGAITMON_CORS_ORIGINS=https://a.example\n")
    monkeypatch.chdir(tmp_path)
    s = Settings()
    assert (s.auto_migrate, s.port, s.host, s.log_format, s.cors_origin_list) == (
        False, 9123, "0.0.0.0", "json", ["https://a.example"])


def test_create_token_names_the_database_it_writes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    settings = Settings(data_dir=Path("data"))  # relative, as in a .env: depends on the working directory
    monkeypatch.setattr(cli, "get_settings", lambda: settings)
    monkeypatch.setattr(cli, "setup_logging", lambda level, fmt="text": None)
    assert cli.main(["create-token", "--role", "admin"]) == 0
    first = capsys.readouterr().err
    db = (tmp_path / "data" / "gaitmon.sqlite").resolve()
    assert f"database: {db} (new file" in first
    assert cli.main(["create-token", "--role", "admin"]) == 0
    second = capsys.readouterr().err
    assert f"database: {db}\n" in second and "new file" not in second


def test_version_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip() == f"gaitmon {cli.package_version()}"
    assert cli.package_version()[0].isdigit()


def test_serve_uses_host_and_port_settings(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import uvicorn

    seen: dict[str, Any] = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: seen.update(kw))
    settings = Settings(data_dir=tmp_path, host="0.0.0.0", port=8123, auto_migrate=False, job_runner="manual")
    assert cli.cmd_serve(cli.build_parser().parse_args(["serve"]), settings) == 0
    assert (seen["host"], seen["port"]) == ("0.0.0.0", 8123)
    assert cli.cmd_serve(cli.build_parser().parse_args(["serve", "--port", "9000"]), settings) == 0
    assert seen["port"] == 9000


def test_metrics_of_several_processes_are_summed_in_multiprocess_mode(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PROMETHEUS_MULTIPROC_DIR": str(tmp_path)}
    count = "from server.ops import metrics; metrics.batch_ingested(10, stored=True)"
    for _ in range(2):  # two API processes, each counting one stored batch of 10 samples
        subprocess.run([sys.executable, "-c", count], env=env, cwd=repo, check=True, timeout=60)
    scrape = ("from sqlalchemy import create_engine; from sqlalchemy.orm import sessionmaker; "
              "from server.ops import metrics; print(metrics.render(sessionmaker(create_engine('sqlite://'))).decode())")
    out = subprocess.run([sys.executable, "-c", scrape], env=env, cwd=repo, check=True, timeout=60,
                         capture_output=True, text=True).stdout
    assert "gaitmon_samples_ingested_total 20.0" in out
    assert 'gaitmon_batches_total{result="stored"} 2.0' in out


def test_in_memory_windows_answer_as_limits_own_sliding_window_counter(monkeypatch: pytest.MonkeyPatch) -> None:
    """MemoryWindows (memory://) against limits' SlidingWindowCounterRateLimiter on MemoryStorage: the same
    allowed/refused answers, tests and reset times over hits at random times across many window boundaries."""
    import random
    import time as time_module

    from limits.storage import MemoryStorage
    from limits.strategies import SlidingWindowCounterRateLimiter

    from server.ops.rate_limit import MemoryWindows

    now = [1_800_000_000.0]
    monkeypatch.setattr(time_module, "time", lambda: now[0])
    ours, theirs = MemoryWindows(), SlidingWindowCounterRateLimiter(MemoryStorage())
    rng = random.Random(3)
    answers = []
    for item in parse_many("7/second;20/minute;3/10 seconds"):
        for _ in range(600):
            now[0] += rng.choice([0.0, 0.01, 0.2, 0.7, 1.3, 4.0, 11.0])
            ident = rng.choice(["a", "b"])
            answers.append((ours.test(item, ident), theirs.test(item, ident)))
            answers.append((ours.hit(item, ident), theirs.hit(item, ident)))
            answers.append((round(ours.get_window_stats(item, ident).reset_time, 6),
                            round(theirs.get_window_stats(item, ident).reset_time, 6)))
    assert all(a == b for a, b in answers), next((a, b) for a, b in answers if a != b)
    assert {a for a, _ in answers} >= {True, False}  # both answers occur
    now[0] += 3 * 3600 + MemoryWindows.SWEEP_EVERY_S
    ours.hit(parse_many("1/second")[0], "c")
    assert len(ours) == 1  # the dead counters are swept
