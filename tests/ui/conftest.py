"""A real `gaitmon serve` with simulated patients, and headless Chromium from the distribution driven by Playwright.

The server runs on a temporary SQLite database and a free port; data arrive through the public API exactly as the
phone app sends them (simulated IMU sessions on past days, processed by the embedded job runner). Chromium is
``/usr/bin/chromium`` (Debian's package): nothing downloads a browser. Without it the browser tests skip, and
fail under GAITMON_REQUIRE_BROWSER=1 (set by .ci/run).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import pytest

from gaitmon.client import Client
from pipeline.simulate import SimConfig, simulate_session
from server.simulate_cli import session_to_requests, upload
from tests.integration.conftest import REPO, free_port, gaitmon_command, server_env

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
REQUIRE_BROWSER = os.environ.get("GAITMON_REQUIRE_BROWSER") == "1"
SCREENSHOTS = REPO / "tests" / "ui" / "screenshots"
# Sessions of the main patient: days ago and gait pattern (a stiff knee early on, normal walking later).
SESSIONS = [(20, "stiff-knee", 11), (13, "stiff-knee", 12), (6, "normal", 13), (1, "normal", 14)]


@dataclass
class Seeded:
    base_url: str
    admin: str
    clinician_a: str
    clinician_b: str
    device: str
    patient_a: str
    patient_a2: str
    patient_b: str
    sessions_a: list[str] = field(default_factory=list)
    log: Path | None = None


def _cli(args: list[str], env: dict[str, str], cwd: Path) -> str:
    res = subprocess.run(gaitmon_command() + args, env=env, cwd=cwd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout.strip().splitlines()[-1]


def _post(c: httpx.Client, url: str, token: str, body: dict) -> dict:
    r = c.post(url, json=body, headers={"Authorization": f"Bearer {token}"})
    assert r.status_code in (200, 201), r.text
    return r.json()


def _upload_sim(base_url: str, token: str, patient_id: str, started: datetime, pattern: str, seed: int) -> str:
    sim = simulate_session(SimConfig(pattern=pattern, seed=seed, n_strides=40))
    create, batches = session_to_requests(sim, batch_size=500, patient_id=patient_id, started_at=started)
    with Client(base_url, token, timeout_s=60) as c:
        return upload(c, create, batches, concurrency=2, progress=lambda _m: None)


@pytest.fixture(scope="session")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Seeded]:
    tmp = tmp_path_factory.mktemp("ui-server")
    env = server_env(tmp, f"sqlite:///{tmp / 'ui.sqlite'}")
    port = free_port()
    log_path = tmp / "server.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(gaitmon_command() + ["serve", "--port", str(port)], env=env, cwd=tmp, stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            base = f"http://127.0.0.1:{port}"
            admin = _cli(["create-token", "--role", "admin", "--name", "ops"], env, tmp)
            with httpx.Client(base_url=base, timeout=30) as c:
                deadline = time.monotonic() + 60
                while True:
                    assert proc.poll() is None, log_path.read_text()[-3000:]
                    try:
                        if c.get("/healthz").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass
                    assert time.monotonic() < deadline, "server not healthy in 60 s"
                    time.sleep(0.2)
                tok_a = _post(c, "/v1/clinicians", admin, {"name": "Dr Adams"})["token"]
                tok_b = _post(c, "/v1/clinicians", admin, {"name": "Dr Brown"})["token"]
                pa = _post(c, "/v1/patients", tok_a, {"external_id": "KNEE-001", "display_name": "Anna Meier",
                                                      "affected_leg": "left", "timezone": "Europe/Berlin"})["id"]
                pa2 = _post(c, "/v1/patients", tok_a, {"external_id": "KNEE-002", "display_name": "Paul Roth",
                                                       "affected_leg": "right", "timezone": "Europe/Berlin"})["id"]
                pb = _post(c, "/v1/patients", tok_b, {"external_id": "HIP-900", "display_name": "Other Clinic",
                                                      "timezone": "America/New_York"})["id"]
                device = _post(c, f"/v1/patients/{pa}/device-tokens", tok_a, {"name": "phone"})["token"]
            now = datetime.now(UTC).replace(microsecond=0)
            at_nine = now.replace(hour=8, minute=30, second=0)
            sids = [_upload_sim(base, device, pa, at_nine - timedelta(days=d), pattern, seed)
                    for d, pattern, seed in SESSIONS]
            sid_b = _upload_sim(base, tok_b, pb, at_nine - timedelta(days=2), "normal", 21)
            # 9.25 days before the pages are read, whatever the hour the suite runs: far from a whole-day boundary
            sid_a2 = _upload_sim(base, tok_a, pa2, now - timedelta(days=9, hours=6), "slow", 22)
            with Client(base, admin) as c:
                for sid in [*sids, sid_b, sid_a2]:
                    assert c.wait_for_processing(sid, timeout_s=180).status == "done"
            yield Seeded(base, admin, tok_a, tok_b, device, pa, pa2, pb, sids, log_path)
        finally:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


@pytest.fixture(scope="session")
def browser() -> Iterator[object]:
    if not Path(CHROMIUM).exists():
        reason = f"{CHROMIUM} is missing (apt-get install chromium)"
        if REQUIRE_BROWSER:
            pytest.fail(reason + " (GAITMON_REQUIRE_BROWSER=1)")
        pytest.skip(reason)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        if REQUIRE_BROWSER:
            pytest.fail(f"playwright is not installed: {exc}")
        pytest.skip(f"playwright is not installed: {exc}")
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def copy_screenshot(name: str, target: Path) -> None:
    """Refresh the README's picture from a test screenshot (only when asked: GAITMON_UPDATE_DOCS_SCREENSHOT=1)."""
    if os.environ.get("GAITMON_UPDATE_DOCS_SCREENSHOT") == "1":
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(SCREENSHOTS / name, target)
