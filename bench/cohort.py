"""The attention list on a simulated cohort with known trajectories: precision and recall per flag.

    .venv/bin/python -m bench.cohort                       # report seeds (the figures of the README)
    .venv/bin/python -m bench.cohort --split tune          # the seeds the thresholds were chosen on
    .venv/bin/python -m bench.cohort --per-group 2 --workers 2   # a quick look
    .venv/bin/python -m bench.cohort --split tune --db-url sqlite:////tmp/t.sqlite --evaluate-only  # read again

Every patient walks 8 sessions of ~40 s (60 s recordings, thigh + shank of the affected left leg; ``--both-legs``
for both) dated over the last 27 days,
simulated by ``pipeline.simulate`` with the truth set per group, with 0-5 % bursty (Gilbert-Elliott) packet loss
drawn per patient; half the patients have a prescribed schedule of 2 sessions/week, half none:

| group | truth (peak swing flexion, both legs) | expected flags |
| --- | --- | --- |
| improving | 48 -> 64 deg over the 27 days | improving |
| declining | 64 -> 50 deg | declining |
| stable | 64 deg | none |
| plateau | 52 deg | stalled |
| silent | 64 deg, sessions only in days 27-13 (silent for the last 12 days) | silent |
| sensor_off | 64 deg; in the last session the left shank sensor falls off and stops at 35-60 % of it | sensor_trouble |
| running | running sessions | none |

Sessions are simulated in parallel processes. The first ``--api-per-group`` patients of each group (default 2 of
15) are uploaded through the HTTP API of an in-process server (create, batches, complete); the others' sessions
are stored as raw batches directly, as the upload path stores them (``tests.support.seed.add_stream_batches``), so
they meet the same job runner, pipeline, summaries and attention rows and skip only the HTTP upload. Everything is
processed by ``--workers`` job-runner processes claiming from the same database (the exactly-once claim of
:mod:`server.processing.jobs`), and the list is read from ``GET /v1/attention`` (every page).
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.simulate import SimConfig, simulate_session
from server.simulate_cli import session_to_requests

FLAGS = ("declining", "improving", "stalled", "silent", "sensor_trouble")
SPLITS = {"tune": 1000, "dev": 2000, "report": 3000}  # seed bases: thresholds chosen on "tune" and "dev" only
LOSSES = (0.0, 0.01, 0.02, 0.03, 0.04, 0.05)
N_SESSIONS = 8
# The simulator's default gait: mean true peak swing flexion and minimum flexion of steady strides (seeds 0-9);
# knee_scale stretches the curve above its minimum, so a target peak T needs scale (T - MIN) / (PEAK - MIN).
DEFAULT_PEAK_DEG = 61.65
DEFAULT_MIN_DEG = 3.42


@dataclass(frozen=True)
class Group:
    """A trajectory and the flags a correct attention list shows for it."""

    expected: frozenset[str]
    start_deg: float
    end_deg: float
    pattern: str = "normal"
    last_day: float = 0.5  # days before now of the last session
    fall_off: bool = False


GROUPS: dict[str, Group] = {
    "improving": Group(frozenset({"improving"}), 48.0, 64.0),
    "declining": Group(frozenset({"declining"}), 64.0, 50.0),
    "stable": Group(frozenset(), 64.0, 64.0),
    "plateau": Group(frozenset({"stalled"}), 52.0, 52.0),
    "silent": Group(frozenset({"silent"}), 64.0, 64.0, last_day=13.0),
    "sensor_off": Group(frozenset({"sensor_trouble"}), 64.0, 64.0, fall_off=True),
    "running": Group(frozenset(), 64.0, 64.0, pattern="running"),
}


@dataclass(frozen=True)
class PlannedSession:
    """One session to simulate: who, when, what."""

    patient: int
    index: int
    seed: int
    days_ago: float
    peak_deg: float
    pattern: str
    packet_loss: float
    cut_left_shank: float | None  # fraction of the session after which the left shank sends nothing
    duration_s: float = 60.0
    legs: tuple[str, ...] = ("left", "right")


@dataclass(frozen=True)
class PlannedPatient:
    """One simulated patient."""

    index: int
    group: str
    packet_loss: float
    prescribed: float | None
    via_api: bool = True  # uploaded through the HTTP API, else stored as raw batches directly (same processing)


def plan(split: str, per_group: int, groups: list[str] | None = None, legs: tuple[str, ...] = ("left",),
         api_per_group: int | None = None) -> tuple[list[PlannedPatient], list[PlannedSession]]:
    """Patients and sessions of one seed split (deterministic; a subset of groups keeps their seeds). The first
    ``api_per_group`` patients of each group (None: all) are uploaded through the API."""
    base = SPLITS[split]
    patients, sessions = [], []
    for g_i, (name, g) in enumerate(GROUPS.items()):
        if groups and name not in groups:
            continue
        for j in range(per_group):
            i = len(patients)
            seed = base + 100 * g_i + j
            rng = np.random.default_rng(seed)
            loss = float(LOSSES[(j + g_i) % len(LOSSES)])
            patients.append(PlannedPatient(i, name, loss, 2.0 if j % 2 == 0 else None,
                                           via_api=api_per_group is None or j < api_per_group))
            days = np.linspace(27.0, g.last_day, N_SESSIONS) + rng.uniform(-0.2, 0.2, N_SESSIONS)
            days[-1] = g.last_day + rng.uniform(0.0, 0.3)
            for k, d in enumerate(days):
                frac = k / (N_SESSIONS - 1)
                cut = float(rng.uniform(0.35, 0.6)) if g.fall_off and k == N_SESSIONS - 1 else None
                sessions.append(PlannedSession(i, k, seed * 10 + k, float(d),
                                               g.start_deg + frac * (g.end_deg - g.start_deg), g.pattern, loss, cut,
                                               legs=legs))
    return patients, sessions


def _simulated_streams(s: PlannedSession, now_iso: str) -> tuple[int, int, datetime, str, list]:
    """The raw streams of one planned session (the left shank cut where the sensor falls off)."""
    scale = (s.peak_deg - DEFAULT_MIN_DEG) / (DEFAULT_PEAK_DEG - DEFAULT_MIN_DEG)
    cfg = SimConfig(pattern=s.pattern, seed=s.seed, duration_s=s.duration_s, activities=("standing",), legs=s.legs,
                    knee_scale=(scale, scale), packet_loss=s.packet_loss, loss_model="bursty")
    sim = simulate_session(cfg)
    streams = list(sim.streams)
    if s.cut_left_shank is not None:
        t_cut = s.cut_left_shank * sim.duration_s
        cut = []
        for st in streams:
            if st.leg == "left" and st.segment == "shank":
                keep = np.asarray(st.t_s) < t_cut
                st = dataclasses.replace(st, t_s=st.t_s[keep], gyr=st.gyr[keep], acc=st.acc[keep])
            cut.append(st)
        streams = cut
    started = datetime.fromisoformat(now_iso) - timedelta(days=s.days_ago)
    return s.patient, s.index, started, sim.activity, streams, sim


def _simulate(s: PlannedSession, now_iso: str) -> tuple[int, int, dict, list[dict]]:
    """The upload requests (create body, batch bodies) of one planned session."""
    _, _, started, _, streams, sim = _simulated_streams(s, now_iso)
    create, batches = session_to_requests(dataclasses.replace(sim, streams=streams), batch_size=3000,
                                          started_at=started, client_session_id=f"cohort-{s.seed}")
    return s.patient, s.index, create, batches


def _simulate_direct(s: PlannedSession, now_iso: str) -> tuple[int, int, datetime, str, list]:
    patient, index, started, activity, streams, _ = _simulated_streams(s, now_iso)
    return patient, index, started, activity, streams


def _process(url: str, worker: int) -> int:
    from server.db import make_engine, make_sessionmaker
    from server.processing.jobs import run_queued

    engine = make_engine(url)
    try:
        return run_queued(make_sessionmaker(engine), worker_id=f"cohort-{worker}")
    finally:
        engine.dispose()


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _simulated(fn: Any, sessions: list[PlannedSession], now_iso: str, workers: int) -> Iterator[tuple]:
    if not sessions:
        return
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        yield from pool.map(fn, sessions, [now_iso] * len(sessions), chunksize=2)


def _upload(client: Any, dev: dict[str, str], patient_id: str, create: dict, batches: list[dict]) -> None:
    r = client.post("/v1/sessions", json={**create, "patient_id": patient_id}, headers=dev)
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    for b in batches:
        r = client.post(f"/v1/sessions/{sid}/batches", json=b, headers=dev)
        assert r.status_code in (200, 201), r.text
    r = client.post(f"/v1/sessions/{sid}/complete", headers=dev)
    assert r.status_code == 202, r.text


def _store_direct(factory: Any, patient_id: str, index: int, started: datetime, activity: str,
                  streams: list) -> None:
    """A completed session stored as the upload path stores it (session, sensors, raw batches), queued."""
    from server.db import new_id
    from server.sessions.models import Session
    from server.utc import utcnow
    from tests.support.seed import add_stream_batches

    with factory() as db:
        sid = new_id()
        db.add(Session(id=sid, patient_id=patient_id, client_session_id=f"cohort-direct-{sid}", started_at=started,
                       activity=activity, status="queued", completed_at=utcnow()))
        db.flush()
        add_stream_batches(db, sid, streams, max(1, int(streams[0].t_s.size // 3000)) if streams else 1)
        db.commit()


def run_cohort(url: str, split: str, per_group: int, workers: int, groups: list[str] | None = None,
               legs: tuple[str, ...] = ("left",), api_per_group: int | None = None) -> dict[str, Any]:
    """Simulate, upload (or store directly), process and read the attention list; returns the list and the plan."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.auth.service import issue_token
    from server.config import Settings
    from server.migrate import upgrade_to_head

    patients, sessions = plan(split, per_group, groups, legs, api_per_group)
    by_index = {p.index: p for p in patients}
    now = datetime.now(UTC).replace(microsecond=0)
    upgrade_to_head(url)
    app = create_app(Settings(database_url=url, job_runner="manual", data_dir=Path(tempfile.gettempdir())))
    timings: dict[str, float] = {}
    with TestClient(app) as client:
        with app.state.sessionmaker() as db:
            _, admin = issue_token(db, role="admin", name="cohort admin")
            db.commit()
        r = client.post("/v1/clinicians", json={"name": "Dr. Cohort"}, headers=_bearer(admin))
        clin = r.json()["token"]
        ids, devices = {}, {}
        for p in patients:
            body = {"display_name": f"{p.group}-{p.index}", "affected_leg": "left",
                    "prescribed_sessions_per_week": p.prescribed}
            r = client.post("/v1/patients", json=body, headers=_bearer(clin))
            assert r.status_code == 201, r.text
            ids[p.index] = r.json()["id"]
            r = client.post(f"/v1/patients/{ids[p.index]}/device-tokens", headers=_bearer(clin))
            devices[p.index] = r.json()["token"]
        t0 = time.perf_counter()
        api = [s for s in sessions if by_index[s.patient].via_api]
        direct = [s for s in sessions if not by_index[s.patient].via_api]
        for n, (pi, _, create, batches) in enumerate(_simulated(_simulate, api, now.isoformat(), workers), 1):
            _upload(client, _bearer(devices[pi]), ids[pi], create, batches)
            if n % 40 == 0 or n == len(api):
                log(f"  uploaded {n}/{len(api)} sessions through the API ({time.perf_counter() - t0:.0f} s)")
        timings["simulate_upload_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for n, (pi, k, started, activity, streams) in enumerate(
                _simulated(_simulate_direct, direct, now.isoformat(), workers), 1):
            _store_direct(app.state.sessionmaker, ids[pi], k, started, activity, streams)
            if n % 100 == 0 or n == len(direct):
                log(f"  stored {n}/{len(direct)} sessions directly ({time.perf_counter() - t0:.0f} s)")
        timings["simulate_store_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            processed = sum(pool.map(_process, [url] * workers, range(workers)))
        timings["process_s"] = time.perf_counter() - t0
        log(f"  processed {processed} sessions ({timings['process_s']:.0f} s)")
        att = _read_list(client, _bearer(clin))
        trends = {}
        for p in patients:
            r = client.get(f"/v1/patients/{ids[p.index]}/trends", params={"leg": "left"}, headers=_bearer(clin))
            assert r.status_code == 200, r.text
            trends[p.index] = r.json()
    return {"patients": patients, "ids": ids, "attention": att, "timings": timings, "trends": trends}


def _read_list(client: Any, headers: dict[str, str]) -> dict[str, Any]:
    """Every page of ``GET /v1/attention``, the items concatenated."""
    params: dict[str, Any] = {"limit": 200}
    out: dict[str, Any] | None = None
    while True:
        r = client.get("/v1/attention", params=params, headers=headers)
        assert r.status_code == 200, r.text
        page = r.json()
        if out is None:
            out = page
        else:
            out["items"] += page["items"]
        if not page["next_cursor"]:
            return out
        params["cursor"] = page["next_cursor"]


def reread(url: str, split: str, per_group: int, groups: list[str] | None, params: Any = None,
           api_per_group: int | None = None) -> dict[str, Any]:
    """The attention list of an already filled cohort database, for tuning: with ``params`` computed live (windows
    ending now), else as the API answers it, from the attention rows (recomputed first where the rules changed:
    the production backfill)."""
    from sqlalchemy import select

    from server.db import make_engine, make_sessionmaker
    from server.patients.models import Patient
    from server.trends import service
    from server.trends.attention import attention_list
    from server.trends.summaries import backfill

    patients, _ = plan(split, per_group, groups, api_per_group=api_per_group)
    engine = make_engine(url)
    factory = make_sessionmaker(engine)
    if params is None:
        backfill(factory)
    with factory() as db:
        by_name = dict(db.execute(select(Patient.display_name, Patient.id)).all())
        ids = {p.index: by_name[f"{p.group}-{p.index}"] for p in patients}
        att = attention_list(db, clinician_id=None, params=params, limit=1000, live=params is not None)
        trends = {}
        for p in patients:
            pat = db.get(Patient, ids[p.index])
            trends[p.index] = service.patient_trends(db, pat, metric_name="peak_swing_flexion_deg", leg="left",
                                                     bucket="day", start=None, end=None)
    engine.dispose()
    return {"patients": patients, "ids": ids, "attention": att, "trends": trends,
            "timings": {"simulate_upload_s": 0.0, "process_s": 0.0}}


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def evaluate(patients: list[PlannedPatient], ids: dict[int, str], attention: dict[str, Any]) -> dict[str, Any]:
    """Precision and recall per flag, flags per group, false alarms on flat trajectories by packet loss."""
    flagged: dict[str, set[str]] = {it["patient"]["id"]: {f["kind"] for f in it["flags"]} for it in attention["items"]}
    per_flag = {}
    for kind in FLAGS:
        tp = fp = fn = 0
        for p in patients:
            got = kind in flagged.get(ids[p.index], set())
            want = kind in GROUPS[p.group].expected
            tp += got and want
            fp += got and not want
            fn += want and not got
        per_flag[kind] = {"tp": tp, "fp": fp, "fn": fn,
                          "precision": tp / (tp + fp) if tp + fp else None,
                          "recall": tp / (tp + fn) if tp + fn else None}
    per_group: dict[str, dict[str, int]] = {}
    for p in patients:
        row = per_group.setdefault(p.group, {"n": 0, **{k: 0 for k in FLAGS}})
        row["n"] += 1
        for k in flagged.get(ids[p.index], set()):
            row[k] += 1
    stable = [p for p in patients if p.group == "stable"]
    stable_alarms = sum(1 for p in stable if flagged.get(ids[p.index], set()) & {"declining", "sensor_trouble"})
    flat = [p for p in patients if GROUPS[p.group].start_deg == GROUPS[p.group].end_deg
            and GROUPS[p.group].pattern == "normal"]
    flat_declining = sum(1 for p in flat if "declining" in flagged.get(ids[p.index], set()))
    no_trouble = [p for p in patients if "sensor_trouble" not in GROUPS[p.group].expected]
    trouble_alarms = sum(1 for p in no_trouble if "sensor_trouble" in flagged.get(ids[p.index], set()))
    return {"per_flag": per_flag, "per_group": per_group, "stable_alarms": stable_alarms, "n_stable": len(stable),
            "flat_declining": flat_declining, "n_flat": len(flat), "trouble_alarms": trouble_alarms,
            "n_no_trouble": len(no_trouble)}


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def report(ev: dict[str, Any], out: dict[str, Any], split: str) -> None:
    """Print the figures (markdown tables, as in the README)."""
    n = len(out["patients"])
    print(f"\ncohort: {n} patients x {N_SESSIONS} sessions, split '{split}' (seed base {SPLITS[split]}), "
          f"bursty packet loss 0-5 %; {sum(p.via_api for p in out['patients'])} patients uploaded through the API, "
          f"the others stored as raw batches; simulate+upload {out['timings']['simulate_upload_s']:.0f} s, "
          f"simulate+store {out['timings'].get('simulate_store_s', 0.0):.0f} s, "
          f"process {out['timings']['process_s']:.0f} s")
    print("\n| flag | TP | FP | FN | precision | recall |\n| --- | --- | --- | --- | --- | --- |")
    for kind, r in ev["per_flag"].items():
        print(f"| {kind} | {r['tp']} | {r['fp']} | {r['fn']} | {_fmt(r['precision'])} | {_fmt(r['recall'])} |")
    print("\n| group | patients | " + " | ".join(FLAGS) + " |\n| --- | --- | " + " | ".join("---" for _ in FLAGS)
          + " |")
    for g, row in ev["per_group"].items():
        print(f"| {g} | {row['n']} | " + " | ".join(str(row[k]) for k in FLAGS) + " |")
    print(f"\nstable patients (0-5 % loss) with declining or sensor_trouble: {ev['stable_alarms']} of {ev['n_stable']}")
    print(f"declining false alarms on flat walking trajectories (stable, plateau, silent, sensor_off): "
          f"{ev['flat_declining']} of {ev['n_flat']}")
    print(f"sensor_trouble false alarms on patients without a sensor fault: {ev['trouble_alarms']} of "
          f"{ev['n_no_trouble']}")
    print(f"(load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")


def reasons(out: dict[str, Any]) -> None:
    """Every flag with its sentence (``--verbose``)."""
    by_id = {out["ids"][p.index]: p for p in out["patients"]}
    for it in out["attention"]["items"]:
        p = by_id[it["patient"]["id"]]
        for f in it["flags"]:
            print(f"  {p.group:<10} loss {100 * p.packet_loss:.0f} %  {f['kind']:<14} {f['reason']}")
    for p in out["patients"]:
        tr = out["trends"][p.index]
        means = [b["mean"] for b in tr["buckets"]]
        print(f"  {p.group:<10} loss {100 * p.packet_loss:.0f} %  trend {tr['trend']['slope_per_week']} "
              f"CI {tr['trend']['ci95']} p {tr['trend']['p_value']} n {tr['trend']['n']} day means {means} "
              f"strides {[b['n_strides'] for b in tr['buckets']]}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=sorted(SPLITS), default="report")
    ap.add_argument("--per-group", type=int, default=15)
    ap.add_argument("--api-per-group", type=int, default=2,
                    help="patients per group uploaded through the HTTP API; the others are stored as raw batches "
                         "directly (same simulator, job runner and pipeline; only the HTTP upload is skipped)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--db-url", default=None, help="database to use (default: a temporary SQLite file)")
    ap.add_argument("--verbose", action="store_true", help="print every flag's reason and each patient's trend")
    ap.add_argument("--groups", nargs="*", choices=sorted(GROUPS), help="only these groups (same seeds)")
    ap.add_argument("--both-legs", action="store_true",
                    help="instrument both legs (default: the affected left leg only, half the simulation time)")
    ap.add_argument("--evaluate-only", action="store_true",
                    help="read the list again from --db-url (a database an earlier run filled with the same split, "
                         "--per-group and --groups) without simulating")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.evaluate_only:
        out = reread(args.db_url, args.split, args.per_group, args.groups, api_per_group=args.api_per_group)
        ev = evaluate(out["patients"], out["ids"], out["attention"])
        if args.verbose:
            reasons(out)
        report(ev, out, args.split)
        return
    with tempfile.TemporaryDirectory() as tmp:
        url = args.db_url or f"sqlite:///{Path(tmp) / 'cohort.sqlite'}"
        out = run_cohort(url, args.split, args.per_group, args.workers, args.groups,
                         ("left", "right") if args.both_legs else ("left",), args.api_per_group)
        ev = evaluate(out["patients"], out["ids"], out["attention"])
    if args.verbose:
        reasons(out)
    report(ev, out, args.split)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
