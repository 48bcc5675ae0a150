"""Peak RSS of a real ``gaitmon worker`` processing the 12-sample span attack (issue 10: <= 200 MB).

    python -m bench.span_attack [--pg-url postgresql+psycopg://postgres@127.0.0.1:5432/postgres] [--db NAME]

The attack: one session, two sensors declared at 2000 Hz, 3 samples each at t = 0 and 3 at t = 2e6 ms (a 2000-s
span: 4 million grid points per sensor at the declared rate for 12 samples). ``/complete`` refuses it (422); here
it is queued anyway, as a session queued before that check existed would be (status set to ``queued`` in the
database, its procrastinate job deferred), and processed by a ``gaitmon worker`` subprocess on a fresh PostgreSQL
database. Printed: the worker's ``VmHWM`` (peak resident set, imports included) from ``/proc`` when idle and after
the job ended, the session's outcome and error, and the bound. The worker runs from this interpreter's
installation (its ``gaitmon`` script), so a venv without numba measures the default install.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sqlalchemy import create_engine, text, update

from bench.ingest import _fresh_pg, _gaitmon

BOUND_MB = 200.0
REPO = Path(__file__).resolve().parents[1]
SENSORS = [{"sensor_id": f"L-{seg}", "leg": "left", "segment": seg, "sample_rate_hz": 2000, "gyro_unit": "deg/s",
            "acc_unit": "m/s2"} for seg in ("thigh", "shank")]


def _status_mb(pid: int) -> dict[str, float]:
    """``VmHWM`` and ``VmRSS`` [MB] of a process."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, val = line.partition(":")
        if key in ("VmHWM", "VmRSS"):
            out[key] = int(val.split()[0]) / 1024
    return out


def _api(url: str, tmp: Path):  # noqa: ANN202 - (app, TestClient, patient id, device token)
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.auth.service import issue_token
    from server.config import Settings

    app = create_app(Settings(database_url=url, job_runner="procrastinate", data_dir=tmp))
    with app.state.sessionmaker() as db:
        _, admin = issue_token(db, role="admin", name="span attack bench")
        db.commit()
    c = TestClient(app)
    clin = _post(c, "/v1/clinicians", {"name": "Dr. Bench"}, admin)["token"]
    pid = _post(c, "/v1/patients", {"external_id": "span-attack"}, clin)["id"]
    return app, c, pid, _post(c, f"/v1/patients/{pid}/device-tokens", {}, clin)["token"]


def _post(c, path: str, body: dict, token: str) -> dict:  # noqa: ANN001
    r = c.post(path, json=body, headers={"Authorization": f"Bearer {token}"})
    if r.status_code not in (200, 201, 202):
        raise RuntimeError(f"{path}: {r.status_code} {r.text}")
    return r.json()


def _upload_normal(c, pid: str, dev: str, minutes: float) -> str:  # noqa: ANN001
    """A simulated left-leg walking session of ``minutes``, uploaded and completed (processed by the worker)."""
    from pipeline.simulate import SimConfig, simulate_session

    sim = simulate_session(SimConfig(pattern="normal", fs_hz=100.0, seed=100, duration_s=minutes * 60.0))
    streams = [s for s in sim.streams if s.leg == "left"]
    sensors = [{"sensor_id": s.sensor_id, "leg": s.leg, "segment": s.segment, "sample_rate_hz": s.fs_hz,
                "gyro_unit": s.gyro_unit, "acc_unit": s.acc_unit} for s in streams]
    sid = _post(c, "/v1/sessions", {"patient_id": pid, "client_session_id": "warm", "activity": "walking",
                                    "started_at": "2026-11-21T08:30:00+01:00", "sensors": sensors}, dev)["id"]
    for s in streams:
        for seq, a in enumerate(range(0, len(s.t_s), 500)):
            b = min(a + 500, len(s.t_s))
            _post(c, f"/v1/sessions/{sid}/batches", {
                "sensor_id": s.sensor_id, "seq": seq, "t0_ms": float(s.t_s[a] * 1000.0),
                "gyro": s.gyr[a:b].round(4).tolist(), "acc": s.acc[a:b].round(4).tolist(),
                "timestamps_ms": (s.t_s[a:b] * 1000.0).tolist()}, dev)
    _post(c, f"/v1/sessions/{sid}/complete", {}, dev)
    return sid


def _queue_attack(url: str, app, c, pid: str, dev: str) -> str:  # noqa: ANN001
    """Create the attack session through the API (in this process), mark it queued, defer its job."""
    from server.processing.worker import defer_session
    from server.sessions.models import Session

    sid = _post(c, "/v1/sessions", {"patient_id": pid, "client_session_id": "span", "activity": "walking",
                                    "started_at": "2026-11-21T09:30:00+01:00", "sensors": SENSORS}, dev)["id"]
    for s in SENSORS:
        for seq, t0 in enumerate((0.0, 2e6)):
            _post(c, f"/v1/sessions/{sid}/batches", {
                "sensor_id": s["sensor_id"], "seq": seq, "t0_ms": t0, "gyro": [[1.0, 2.0, 3.0]] * 3,
                "acc": [[0.0, 0.0, 9.81]] * 3, "timestamps_ms": [t0, t0 + 0.5, t0 + 1.0]}, dev)
    refused = c.post(f"/v1/sessions/{sid}/complete", headers={"Authorization": f"Bearer {dev}"}).status_code
    with app.state.sessionmaker() as db:  # as if queued before the /complete check existed
        db.execute(update(Session).where(Session.id == sid).values(status="queued"))
        db.commit()
    defer_session(url, sid)
    print(f"- /complete answered {refused}; session {sid} queued anyway and its job deferred")
    return sid


def _wait(engine, sid: str, timeout_s: float) -> tuple[str | None, str | None]:  # noqa: ANN001
    """Status and error of a session once it and its procrastinate job have ended."""
    deadline = time.monotonic() + timeout_s
    status = error = None
    while time.monotonic() < deadline:
        with engine.connect() as conn:
            status, error = conn.execute(text("SELECT status, error FROM sessions WHERE id = :i"), {"i": sid}).one()
            job = conn.execute(text("SELECT status FROM procrastinate_jobs WHERE queueing_lock = :i OR "
                                    "args->>'session_id' = :i ORDER BY id DESC LIMIT 1"), {"i": sid}).scalar()
        if status in ("failed", "done") and job in ("succeeded", "failed"):
            break
        time.sleep(0.2)
    return status, error


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.span_attack", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pg-url", default="postgresql+psycopg://postgres@127.0.0.1:5432/postgres")
    ap.add_argument("--db", default=f"gaitmon_span_{os.getpid()}", help="database to (re)create for the run")
    ap.add_argument("--timeout-s", type=float, default=180.0)
    ap.add_argument("--warm-minutes", type=float, default=0.0,
                    help="first a normal simulated session of this length, processed by the same worker (a worker "
                         "that has processed sessions before: its pipeline imported)")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="gaitmon-span-"))
    url = _fresh_pg(args.pg_url, args.db)
    env = {k: v for k, v in os.environ.items() if not k.startswith("GAITMON_")}
    env.update(GAITMON_DATABASE_URL=url, GAITMON_JOB_RUNNER="procrastinate", GAITMON_DATA_DIR=str(tmp / "data"),
               GAITMON_LOG_LEVEL="WARNING", PYTHONPATH=str(REPO) + os.pathsep + env.get("PYTHONPATH", ""))
    subprocess.run(_gaitmon() + ["migrate"], env=env, check=True, capture_output=True, timeout=180, cwd=REPO)
    log = open(tmp / "worker.log", "w")  # noqa: SIM115 - closed below
    worker = subprocess.Popen(_gaitmon() + ["worker"], env=env, stdout=log, stderr=subprocess.STDOUT, cwd=REPO,
                              start_new_session=True)
    try:
        time.sleep(8.0)  # imports, schema check, the start-up recovery
        if worker.poll() is not None:
            raise RuntimeError(f"worker exited: {(tmp / 'worker.log').read_text()[-2000:]}")
        idle = _status_mb(worker.pid)
        app, c, pid, dev = _api(url, tmp)
        engine = create_engine(url)
        warm = None
        if args.warm_minutes > 0:
            wid = _upload_normal(c, pid, dev, args.warm_minutes)
            warm = (_wait(engine, wid, args.timeout_s)[0], _status_mb(worker.pid))
        sid = _queue_attack(url, app, c, pid, dev)
        status, error = _wait(engine, sid, args.timeout_s)
        engine.dispose()
        c.close()
        after = _status_mb(worker.pid)
    finally:
        os.killpg(worker.pid, signal.SIGTERM)
        try:
            worker.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(worker.pid, signal.SIGKILL)
            worker.wait()
        log.close()
        admin = create_engine(args.pg_url, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{args.db}" WITH (FORCE)'))
        admin.dispose()
    try:
        import numba  # noqa: F401
        install = "with the compiled loops (numba)"
    except ImportError:
        install = "default install (no numba)"
    load = os.getloadavg()
    verdict = "met" if after["VmHWM"] <= BOUND_MB else "MISSED"
    print(f"\n## Span attack, one `gaitmon worker` on PostgreSQL ({install}; {sys.executable}; load average "
          f"{load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f})\n")
    print("| figure | value |")
    print("|---|---|")
    print(f"| worker VmHWM idle (imports, start-up) | {idle['VmHWM']:.0f} MB |")
    if warm is not None:
        print(f"| worker VmHWM after a normal {args.warm_minutes:g}-min one-leg session ({warm[0]}) | "
              f"{warm[1]['VmHWM']:.0f} MB |")
    print(f"| worker VmHWM after the job | **{after['VmHWM']:.0f} MB** (bound <= {BOUND_MB:.0f} MB: {verdict}) |")
    print(f"| worker VmRSS after the job | {after['VmRSS']:.0f} MB |")
    print(f"| session outcome | {status}: {error} |")
    return 0 if after["VmHWM"] <= BOUND_MB and status == "failed" else 1


if __name__ == "__main__":
    raise SystemExit(main())
