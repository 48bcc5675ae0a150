"""Server time of each clinician page for a patient with a year of daily sessions (target: < 300 ms each).

    .venv/bin/python -m bench.pages                     # SQLite, 365 days x 2 legs x ~500 strides (a few minutes)
    .venv/bin/python -m bench.pages --days 60 --repeats 5   # quick look
    .venv/bin/python -m bench.pages --server-repo /work/old-pages --rounds 2   # this code and an older checkout

Seeds, on a temporary SQLite database: one clinician; ``--cohort`` other patients (six weeks of summaries, as in
bench.trends) so "My patients" has a real attention list; one patient with a daily session of both legs for
``--days`` days (Stride rows and trend summaries through the production ``refresh_session``); and, on the last day,
one real simulated recording uploaded as raw batches and processed by the job runner (so the session page has a
stored knee-angle trace). Then it signs in through the login form and times each page in process (FastAPI
TestClient: cookie check, data, SVG, template), median and p95 of ``--repeats`` requests after one warm-up.

``--server-repo`` (repeatable): the pages of each named checkout are timed too, on a copy of the same seeded
database, in a process of their own whose ``server`` package is that checkout's (this file's timing function is
loaded into it); this code and each checkout take turns ``--rounds`` times and every round prints its load average,
so the figures are side by side in one run.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

# Nothing of this repository is imported at module level: the timing function runs in a process whose ``server``
# package may be another checkout's (--server-repo).
REPO = Path(__file__).resolve().parents[1]
CHILD = "import runpy, sys; runpy.run_path(sys.argv[1], run_name='bench_pages_timing')['timing_child'](sys.argv[2])"


def seed_year_both_legs(factory, clinician_id: str, days: int, strides: int) -> str:  # noqa: ANN001
    from bench.trends import NOW, log
    from server.patients.models import Patient
    from tests.support.seed import add_session

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
    from bench.trends import NOW
    from pipeline.simulate import SimConfig, simulate_session
    from server.processing.jobs import process_one
    from server.sessions.models import Session
    from tests.support.seed import add_stream_batches

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


def sign_in(client: Any, token: str) -> None:
    form = client.get("/ui/login").text
    value = re.search(r'name="form_token" value="([^"]+)"', form).group(1)
    r = client.post("/ui/login", data={"token": token, "form_token": value}, follow_redirects=False)
    assert r.status_code == 303, r.text[:300]


PAGES = (("My patients", "/ui/patients"),
         ("Patient, per day (1 year)", "/ui/patients/{pid}?bucket=day"),
         ("Patient, per week (1 year)", "/ui/patients/{pid}?bucket=week"),
         ("Session (whole trace)", "/ui/sessions/{sid}"),
         ("Session (zoomed 20-40 s)", "/ui/sessions/{sid}?start=20&end=40"))


def _p50_p95(xs: list[float]) -> tuple[float, float]:
    xs = sorted(xs)
    return statistics.median(xs), xs[min(len(xs) - 1, int(round(0.95 * (len(xs) - 1))))]


def time_pages(cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """Wall p50/p95 and CPU p50 (this process, both threads of the TestClient) of every page, cold and warm, with
    the ``server`` package this process imports; ``cfg``: database url, data dir, token, patient and session id,
    repeats, and whether to time the estimator comparison."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings
    from server.ui import data as ui_data

    app = create_app(Settings(database_url=cfg["url"], data_dir=Path(cfg["data_dir"]), job_runner="manual"))
    out: list[dict[str, Any]] = []
    with TestClient(app) as client:
        sign_in(client, cfg["token"])
        for name, template in PAGES:
            if cfg.get("only") and cfg["only"] not in name:
                continue
            path = template.format(pid=cfg["pid"], sid=cfg["sid"])
            for state in ("cold", "warm"):
                wall, cpu = [], []
                for i in range(cfg["repeats"] + 1):  # the first request warms caches and the connection pool
                    if state == "cold":
                        ui_data.clear_cache()
                    t, c = time.perf_counter(), time.process_time()
                    r = client.get(path)
                    if i:
                        wall.append((time.perf_counter() - t) * 1000.0)
                        cpu.append((time.process_time() - c) * 1000.0)
                    assert r.status_code == 200, (path, r.status_code, r.text[:300])
                p50, p95 = _p50_p95(wall)
                out.append({"page": name, "state": state, "wall_p50": p50, "wall_p95": p95,
                            "cpu_p50": statistics.median(cpu), "kb": len(r.content) / 1024})
        if cfg.get("compare"):
            t = time.perf_counter()
            assert client.get(f"/ui/sessions/{cfg['sid']}/compare").status_code == 200
            first = (time.perf_counter() - t) * 1000.0
            again = []
            for _ in range(3):
                t = time.perf_counter()
                client.get(f"/ui/sessions/{cfg['sid']}/compare")
                again.append((time.perf_counter() - t) * 1000.0)
            out.append({"page": "Estimator comparison", "first": first, "cached": statistics.median(again)})
    return out


def timing_child(cfg_json: str) -> None:
    """Entry of a --server-repo process: time the pages, print the rows as JSON on the last line."""
    rows = time_pages(json.loads(cfg_json))
    sys.stdout.write("\n" + json.dumps(rows) + "\n")


def time_checkout(repo: Path, cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """:func:`time_pages` in a process that imports ``server`` from ``repo``."""
    env = dict(os.environ, PYTHONPATH=str(repo))
    r = subprocess.run([sys.executable, "-c", CHILD, str(Path(__file__).resolve()), json.dumps(cfg)], cwd=repo,
                       env=env, capture_output=True, text=True, timeout=3600)
    if r.returncode != 0:
        raise RuntimeError(f"pages of {repo} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _revision(repo: Path) -> str:
    r = subprocess.run(["git", "-C", str(repo), "log", "-1", "--format=%h %s"], capture_output=True, text=True)
    return (r.stdout.strip() or "?")[:60]


def print_rows(rows: list[dict[str, Any]]) -> None:
    print(f"  {'page':<34} {'wall p50':>9} {'wall p95':>9} {'CPU p50':>9}  size")
    for row in rows:
        if "state" in row:
            print(f"  {row['page'] + ', ' + row['state']:<34} {row['wall_p50']:6.1f} ms {row['wall_p95']:6.1f} ms "
                  f"{row['cpu_p50']:6.1f} ms  {row['kb']:.0f} kB")
        else:
            print(f"  {row['page']:<28} {row['first']:7.0f} ms first (re-runs 5 estimators), "
                  f"{row['cached']:.1f} ms cached")


def main(argv: list[str] | None = None) -> None:
    from bench.trends import log, seed_cohort
    from server.auth.service import create_clinician
    from server.db import make_engine, make_sessionmaker
    from server.migrate import upgrade_to_head

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=365)
    ap.add_argument("--strides", type=int, default=500, help="strides per leg per daily session")
    ap.add_argument("--cohort", type=int, default=40, help="other patients of the clinician")
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the real recording")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--server-repo", type=Path, action="append", default=[],
                    help="another checkout whose pages are timed on the same data, alternately with this code")
    ap.add_argument("--rounds", type=int, default=2, help="turns of each code with --server-repo")
    ap.add_argument("--only", default="", help="time only the pages whose name contains this (e.g. Session)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        db_file = Path(tmp) / "pages.sqlite"
        url = f"sqlite:///{db_file}"
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
        cfg = {"url": url, "data_dir": str(Path(tmp) / "data"), "token": token, "pid": pid, "sid": sid,
               "repeats": args.repeats, "only": args.only}
        print(f"clinician pages, SQLite, {args.days} daily sessions, {args.repeats} requests each; target < 300 ms")
        print(f"  load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (wall time grows with "
              f"other load; CPU time does not)")
        print("  cold: trend answers recomputed (first view after a session was processed); "
              "warm: served from the page cache")
        if not args.server_repo:
            print_rows(time_pages({**cfg, "compare": True}))
            sys.stdout.flush()
            return
        # Each code reads its own copy of the seeded database (an older one may write what it keeps differently).
        codes = []
        for k, repo in enumerate([REPO, *args.server_repo]):
            copy = Path(tmp) / f"pages-{k}.sqlite"
            shutil.copyfile(db_file, copy)
            codes.append((repo.resolve(), _revision(repo), {**cfg, "url": f"sqlite:///{copy}"}))
        results: dict[int, list[list[dict[str, Any]]]] = {k: [] for k in range(len(codes))}
        for rnd in range(1, args.rounds + 1):
            for k, (repo, rev, code_cfg) in enumerate(codes):
                rows = time_checkout(repo, code_cfg)
                results[k].append(rows)
                print(f"round {rnd}, {'this code' if k == 0 else 'other'} {rev} ({repo}), "
                      f"load average at its end {os.getloadavg()[0]:.1f}")
                print_rows(rows)
                sys.stdout.flush()
        print("CPU p50 (ms) per round, and this code / other (ratio of the medians over rounds)")
        for row_i, row in enumerate(results[0][0]):
            if "state" not in row:
                continue
            label = f"{row['page']}, {row['state']}"
            mine = [r[row_i]["cpu_p50"] for r in results[0]]
            cells = [" / ".join(f"{x:.0f}" for x in mine)]
            for k in range(1, len(codes)):
                theirs = [r[row_i]["cpu_p50"] for r in results[k]]
                ratio = statistics.median(mine) / statistics.median(theirs)
                cells.append(f"{' / '.join(f'{x:.0f}' for x in theirs)} (x{ratio:.2f})")
            print(f"  {label:<34} this {cells[0]:<16} " + "  ".join(f"other {c}" for c in cells[1:]))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
