"""Server time of each clinician page for a patient with a year of daily sessions (target: < 300 ms each).

    .venv/bin/python -m bench.pages                     # SQLite, 365 days x 2 legs x ~500 strides (a few minutes)
    .venv/bin/python -m bench.pages --days 60 --repeats 5   # quick look

Seeds, on a temporary SQLite database: one clinician; ``--cohort`` other patients (six weeks of summaries, as in
bench.trends) so "My patients" has a real attention list; one patient with a daily session of both legs for
``--days`` days (Stride rows and trend summaries through the production ``refresh_session``); and, on the last day,
one real simulated recording uploaded as raw batches and processed by the job runner (so the session page has a
stored knee-angle trace). Then it signs in through the login form and times each page in process (FastAPI
TestClient: cookie check, data, SVG, template), median and p95 of ``--repeats`` requests after one warm-up.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from bench.trends import NOW, log, seed_cohort, timeit
from pipeline.simulate import SimConfig, simulate_session
from server.app import create_app
from server.auth.service import create_clinician
from server.config import Settings
from server.db import make_engine, make_sessionmaker
from server.migrate import upgrade_to_head
from server.patients.models import Patient
from server.processing.jobs import process_one
from server.sessions.models import Session
from server.ui import data as ui_data
from tests.support.seed import add_session, add_stream_batches


def seed_year_both_legs(factory, clinician_id: str, days: int, strides: int) -> str:  # noqa: ANN001
    rng = np.random.default_rng(5)
    with factory() as db:
        p = Patient(clinician_id=clinician_id, external_id="YEAR-001", display_name="One Year", affected_leg="left",
                    timezone="Europe/Berlin", created_at=NOW - timedelta(days=days + 1))
        db.add(p)
        db.commit()
        pid = p.id
    t0 = time.perf_counter()
    for d in range(days, 0, -1):
        n = int(rng.integers(int(0.9 * strides), int(1.1 * strides) + 1))
        frac = (days - d) / max(days, 1)
        started = (NOW - timedelta(days=d)).replace(hour=8, minute=0) + timedelta(hours=float(rng.uniform(0, 8)))
        legs = {leg: {"n": n, "peak_swing_flexion_deg": rng.normal(base + 15.0 * frac, 3.0, n),
                      "min_flexion_deg": rng.normal(6.0 - 4.0 * frac, 1.0, n),
                      "duration_s": rng.normal(1.1, 0.05, n), "quality": np.where(rng.random(n) < 0.03, 0.2, 1.0)}
                for leg, base in (("left", 42.0), ("right", 58.0))}
        with factory() as db:
            add_session(db, pid, started, legs)
            db.commit()
        if (days - d + 1) % 60 == 0:
            log(f"  one-year patient: {days - d + 1}/{days} sessions ({time.perf_counter() - t0:.0f} s)")
    return pid


def add_recording(factory, patient_id: str, minutes: float) -> str:  # noqa: ANN001
    """A real simulated recording as raw batches, processed by the job runner; returns the session id."""
    sim = simulate_session(SimConfig(seed=3, duration_s=60.0 * minutes))
    with factory() as db:
        sess = Session(patient_id=patient_id, client_session_id="bench-recording", started_at=NOW - timedelta(hours=2),
                       activity="walking", status="queued", completed_at=NOW)
        db.add(sess)
        db.flush()
        add_stream_batches(db, sess.id, sim.streams, 20)
        db.commit()
        sid = sess.id
    assert process_one(factory, sid) == "done"
    return sid


def sign_in(client: TestClient, token: str) -> None:
    form = client.get("/ui/login").text
    value = re.search(r'name="form_token" value="([^"]+)"', form).group(1)
    r = client.post("/ui/login", data={"token": token, "form_token": value}, follow_redirects=False)
    assert r.status_code == 303, r.text[:300]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=365)
    ap.add_argument("--strides", type=int, default=500, help="strides per leg per daily session")
    ap.add_argument("--cohort", type=int, default=40, help="other patients of the clinician")
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the real recording")
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{Path(tmp) / 'pages.sqlite'}"
        upgrade_to_head(url)
        engine = make_engine(url)
        factory = make_sessionmaker(engine)
        with factory() as db:
            clinician, token = create_clinician(db, "Dr Bench")
            db.commit()
        log(f"seeding: {args.cohort} cohort patients, one patient with {args.days} daily sessions x 2 legs x "
            f"~{args.strides} strides, one {args.minutes:g}-minute recording")
        seed_cohort(factory, clinician.id, args.cohort)
        pid = seed_year_both_legs(factory, clinician.id, args.days, args.strides)
        sid = add_recording(factory, pid, args.minutes)
        engine.dispose()
        app = create_app(Settings(database_url=url, data_dir=Path(tmp) / "data", job_runner="manual"))
        with TestClient(app) as client:
            sign_in(client, token)
            pages = [
                ("My patients", "/ui/patients"),
                ("Patient, per day (1 year)", f"/ui/patients/{pid}?bucket=day"),
                ("Patient, per week (1 year)", f"/ui/patients/{pid}?bucket=week"),
                ("Session (whole trace)", f"/ui/sessions/{sid}"),
                ("Session (zoomed 20-40 s)", f"/ui/sessions/{sid}?start=20&end=40"),
            ]
            print(f"clinician pages, SQLite, {args.days} daily sessions, {args.repeats} requests each; target < 300 ms")
            print(f"  load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (wall time grows with "
                  f"other load; CPU time does not)")
            print("  cold: trend answers recomputed (first view after a session was processed); "
                  "warm: served from the page cache")
            print(f"  {'page':<34} {'wall p50':>9} {'wall p95':>9} {'CPU p50':>9}  size")
            for name, path in pages:
                for state in ("cold", "warm"):
                    cpu: list[float] = []

                    def get(path: str = path, cpu: list[float] = cpu, cold: bool = state == "cold") -> None:
                        if cold:
                            ui_data.clear_cache()
                        c0 = time.process_time()
                        r = client.get(path)
                        cpu.append((time.process_time() - c0) * 1000.0)
                        assert r.status_code == 200, (path, r.status_code, r.text[:300])
                    med, p95, *_ = timeit(get, args.repeats)
                    size = len(client.get(path).content)
                    print(f"  {name + ', ' + state:<34} {med:6.1f} ms {p95:6.1f} ms "
                          f"{statistics.median(cpu[1:]):6.1f} ms  {size / 1024:.0f} kB")
            t = time.perf_counter()
            assert client.get(f"/ui/sessions/{sid}/compare").status_code == 200
            first = (time.perf_counter() - t) * 1000.0
            med, *_ = timeit(lambda: client.get(f"/ui/sessions/{sid}/compare"), 3)
            print(f"  {'Estimator comparison':<28} {first:7.0f} ms first (re-runs 5 estimators), {med:.1f} ms cached")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
