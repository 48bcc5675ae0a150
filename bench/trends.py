"""Speed of the trends view: p50/p95 of the one-year daily trend and of the attention list, SQLite and PostgreSQL.

    .venv/bin/python -m bench.trends                       # both databases, full size (takes a few minutes)
    .venv/bin/python -m bench.trends --patients 100 --days 60 --skip-postgres   # quick look

Seeds one clinician with ``--patients`` patients (six weeks of sessions every third day, summaries only: declining,
stable, silent and sensor-trouble patients mixed) and one patient with ``--days`` daily sessions of ``--strides``
strides (Stride rows + summaries through the production ``refresh_session``). Then times, in process:
- the service call (``server.trends.service.patient_trends``, one year, daily buckets),
- the same through HTTP (FastAPI TestClient: auth, validation, JSON) for the trend and ``GET /v1/attention``.
PostgreSQL: a dedicated database (``--pg-db``) is dropped and created on the local server.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, insert, text
from sqlalchemy.engine import make_url

from server.auth.service import create_clinician
from server.config import Settings
from server.db import make_engine, make_sessionmaker, new_id
from server.migrate import upgrade_to_head
from server.patients.models import Patient
from server.sessions.models import Session
from server.trends import service
from server.trends.attention import attention_list
from server.trends.attention.evidence import refresh_patient
from server.trends.models import TrendMetricValues, TrendSessionLeg
from server.trends.summaries import summarise_leg
from server.utc import utcnow
from tests.support.seed import add_session

NOW = datetime.now(UTC).replace(microsecond=0)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _synthetic_leg(rng: np.random.Generator, n: int, peak: float,
                   fallback: float) -> tuple[dict, np.ndarray, np.ndarray]:
    dur = rng.normal(1.1, 0.05, n)
    cols = {"peak_swing_flexion_deg": rng.normal(peak, 3.0, n), "rom_deg": rng.normal(peak - 2, 3.0, n),
            "min_flexion_deg": rng.normal(2.0, 1.0, n), "stance_flexion_deg": rng.normal(15.0, 3.0, n),
            "duration_s": dur, "swing_time_s": 0.4 * dur, "stance_pct": rng.normal(60.0, 2.0, n)}
    quality = np.where(rng.random(n) < 0.03, 0.2, 1.0)
    return cols, quality, rng.random(n) < fallback


def seed_cohort(factory, clinician_id: str, n_patients: int, strides: int = 200) -> None:  # noqa: ANN001
    """Patients with six weeks of sessions every third day, written as summaries (no Stride rows)."""
    rng = np.random.default_rng(7)
    t_start = time.perf_counter()
    for i in range(n_patients):
        kind = ("declining", "stable", "improving", "silent", "sensor")[i % 5]
        pid = new_id()
        sessions, legs, metrics = [], [], []
        days = range(41, 0, -3) if kind != "silent" else range(41, 6, -3)
        for d in days:
            sid = new_id()
            started = NOW - timedelta(days=d, hours=float(rng.uniform(0, 10)))
            peak = {"declining": 45 + 0.4 * d, "improving": 62 - 0.4 * d}.get(kind, 55.0)
            cols, quality, fallback = _synthetic_leg(rng, strides, peak, 0.6 if kind == "sensor" else 0.02)
            leg_row, metric_rows = summarise_leg(cols, quality, fallback, n_gaps=int(rng.poisson(0.2)))
            sessions.append({"id": sid, "patient_id": pid, "client_session_id": sid, "started_at": started,
                             "activity": "walking", "status": "done", "algorithm_version": "bench",
                             "created_at": started, "processed_at": started, "attempts": 1})
            key = {"session_id": sid, "leg": "left", "activity": "walking", "patient_id": pid, "started_at": started}
            legs.append({**key, **leg_row, "algorithm_version": "bench", "refreshed_at": utcnow()})
            metrics.extend({**key, **m} for m in metric_rows)
        with factory() as db:
            db.execute(insert(Patient), [{"id": pid, "clinician_id": clinician_id, "display_name": f"P{i:04d}",
                                          "affected_leg": "left", "timezone": "Europe/Berlin",
                                          "created_at": NOW - timedelta(days=60)}])
            db.execute(insert(Session), sessions)
            db.execute(insert(TrendSessionLeg), legs)
            db.execute(insert(TrendMetricValues), metrics)
            refresh_patient(db, pid)
            db.commit()
        if (i + 1) % 100 == 0 or i + 1 == n_patients:
            log(f"  cohort: {i + 1}/{n_patients} patients ({time.perf_counter() - t_start:.0f} s)")


def seed_year(factory, clinician_id: str, days: int, strides: int) -> str:  # noqa: ANN001
    """One patient with a daily session of ``strides`` strides for ``days`` days (Stride rows + refresh)."""
    rng = np.random.default_rng(11)
    with factory() as db:
        p = Patient(clinician_id=clinician_id, display_name="one year", affected_leg="left",
                    timezone="Europe/Berlin", created_at=NOW - timedelta(days=days + 1))
        db.add(p)
        db.commit()
        pid = p.id
    t_start = time.perf_counter()
    for d in range(days, 0, -1):
        n = int(rng.integers(int(0.9 * strides), int(1.1 * strides) + 1))
        peak = 45.0 + 15.0 * (days - d) / max(days, 1)
        with factory() as db:
            started = (NOW - timedelta(days=d)).replace(hour=8, minute=0) + timedelta(hours=float(rng.uniform(0, 8)))
            add_session(db, pid, started, {"left": {
                "n": n, "peak_swing_flexion_deg": rng.normal(peak, 3.0, n), "duration_s": rng.normal(1.1, 0.05, n),
                "quality": np.where(rng.random(n) < 0.03, 0.2, 1.0)}})
            db.commit()
        done = days - d + 1
        if done % 30 == 0 or done == days:
            log(f"  one-year patient: {done}/{days} sessions ({time.perf_counter() - t_start:.0f} s)")
    return pid


def timeit(fn: Callable[[], object], repeats: int) -> tuple[float, float, float, float]:
    """Wall-clock p50/p95 and this process's CPU time p50/p95 in ms. On the shared machine the CPU time is the
    figure that does not depend on what else runs (for PostgreSQL it leaves out the server's share)."""
    fn()  # warm caches and the connection pool
    ts, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        ts.append((time.perf_counter() - t) * 1000.0)
        cpu.append((time.process_time() - c) * 1000.0)

    def p50_p95(xs: list[float]) -> tuple[float, float]:
        xs = sorted(xs)
        return statistics.median(xs), xs[min(len(xs) - 1, int(round(0.95 * (len(xs) - 1))))]

    return (*p50_p95(ts), *p50_p95(cpu))


def run(name: str, url: str, args: argparse.Namespace) -> list[tuple[str, str, float, float, float, float]]:
    from fastapi.testclient import TestClient

    from server.app import create_app

    log(f"[{name}] migrating {make_url(url).render_as_string(hide_password=True)}")
    upgrade_to_head(url)
    engine = make_engine(url)
    factory = make_sessionmaker(engine)
    with factory() as db:
        clin, token = create_clinician(db, "Dr. Bench")
        db.commit()
        clin_id = clin.id
    t = time.perf_counter()
    seed_cohort(factory, clin_id, args.patients)
    pid = seed_year(factory, clin_id, args.days, args.strides)
    log(f"[{name}] seeded in {time.perf_counter() - t:.0f} s")
    if not url.startswith("sqlite"):
        with engine.connect() as conn:
            conn.execute(text("ANALYZE"))
            conn.commit()

    # midnight a year back: the first daily session (08:00-16:00) is inside whatever the time of day now
    year_start = (NOW - timedelta(days=min(args.days, 365))).replace(hour=0, minute=0, second=0, microsecond=0)

    def trend_service() -> None:
        with factory() as db:
            patient = db.get(Patient, pid)
            out = service.patient_trends(db, patient, metric_name="peak_swing_flexion_deg", leg="left",
                                         bucket="day", start=year_start, end=None)
            assert len(out["buckets"]) == min(args.days, 365)

    def attention_service() -> None:
        with factory() as db:
            attention_list(db, clinician_id=clin_id, limit=50)

    def attention_live() -> None:
        with factory() as db:
            attention_list(db, clinician_id=clin_id, limit=50, live=True)

    results = [(name, "trend 1 year daily (service)", *timeit(trend_service, args.repeats)),
               (name, "attention list (service)", *timeit(attention_service, args.repeats)),
               (name, "attention list, live windows", *timeit(attention_live, max(3, args.repeats // 5)))]
    app = create_app(Settings(database_url=url, job_runner="manual", data_dir=Path(tempfile.gettempdir())))
    headers = {"Authorization": f"Bearer {token}"}
    frm = (NOW - timedelta(days=365)).date().isoformat()
    with TestClient(app) as client:
        def trend_http() -> None:
            r = client.get(f"/v1/patients/{pid}/trends", params={"metric": "peak_swing_flexion_deg",
                                                                 "bucket": "day", "from": frm}, headers=headers)
            assert r.status_code == 200, r.text

        def attention_http() -> None:
            r = client.get("/v1/attention", params={"limit": 50}, headers=headers)
            assert r.status_code == 200, r.text

        results += [(name, "trend 1 year daily (HTTP)", *timeit(trend_http, args.repeats)),
                    (name, "attention list (HTTP)", *timeit(attention_http, args.repeats))]
        r = client.get("/v1/attention", params={"limit": 200}, headers=headers).json()
        kinds: dict[str, int] = {}
        for it in r["items"]:
            for f in it["flags"]:
                kinds[f["kind"]] = kinds.get(f["kind"], 0) + 1
        log(f"[{name}] attention: {r['n_flagged']} of {r['n_patients']} patients flagged; first page flags {kinds}")
    engine.dispose()
    return results


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patients", type=int, default=1000)
    ap.add_argument("--days", type=int, default=365)
    ap.add_argument("--strides", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--pg-url", default="postgresql+psycopg://postgres@127.0.0.1:5432/postgres",
                    help="server to create the bench database on")
    ap.add_argument("--pg-db", default="gaitmon_bench_trends")
    ap.add_argument("--skip-postgres", action="store_true")
    ap.add_argument("--skip-sqlite", action="store_true")
    args = ap.parse_args(argv)

    results = []
    if not args.skip_sqlite:
        with tempfile.TemporaryDirectory() as tmp:
            results += run("sqlite", f"sqlite:///{Path(tmp) / 'bench.sqlite'}", args)
    if not args.skip_postgres:
        admin = create_engine(args.pg_url, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{args.pg_db}" WITH (FORCE)'))
            conn.execute(text(f'CREATE DATABASE "{args.pg_db}"'))
        url = make_url(args.pg_url).set(database=args.pg_db).render_as_string(hide_password=False)
        try:
            results += run("postgres", url, args)
        finally:
            with admin.connect() as conn:
                conn.execute(text(f'DROP DATABASE IF EXISTS "{args.pg_db}" WITH (FORCE)'))
            admin.dispose()

    print(f"\n{args.patients} patients + one with {args.days} daily sessions x ~{args.strides} strides; "
          f"{args.repeats} repeats; target p95 < 50 ms for the trend, < 100 ms for the attention list")
    load = os.getloadavg()
    print(f"(load average at the end of the run: {load[0]:.1f} / {load[1]:.1f} (1 / 5 min) on {os.cpu_count()} CPUs)")
    print(f"{'database':<10} {'measure':<32} {'p50 ms':>8} {'p95 ms':>8} {'cpu p50':>8} {'cpu p95':>8}")
    for db, what, p50, p95, c50, c95 in results:
        print(f"{db:<10} {what:<32} {p50:8.1f} {p95:8.1f} {c50:8.1f} {c95:8.1f}")


if __name__ == "__main__":
    main()
