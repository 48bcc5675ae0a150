"""``gaitmon simulate``: a simulated session as a file in the contract's shapes, or uploaded over HTTP.

    gaitmon simulate --pattern normal --minutes 2 --fs 100 --seed 1 --out session.json
    gaitmon simulate --pattern crouch --server http://127.0.0.1:8000 --token T --patient-id P --wait

The upload goes through :mod:`gaitmon.client` and follows the contract: ``POST /v1/sessions``, gzip'd
``POST .../batches`` of ``--batch-size`` samples per sensor (optionally shuffled and partly duplicated to exercise
idempotency), ``POST .../complete``, then with ``--wait`` polling until processing ends and printing the stride
summary next to the simulator's ground truth. :func:`session_to_requests` is the reusable part (server
integration tests use it).
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import sys
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from gaitmon.client import ApiError, Client, Session
from pipeline.simulate import PATTERNS, SimConfig, SimSession, simulate_session


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def session_to_requests(sim: SimSession, batch_size: int = 50, patient_id: str = "PATIENT_ID",
                        started_at: datetime | None = None, client_session_id: str | None = None,
                        with_timestamps: bool = True) -> tuple[dict, list[dict]]:
    """The ``POST /v1/sessions`` body and every ``POST /v1/sessions/{id}/batches`` body of a simulated session.

    Batches hold at most ``batch_size`` samples of one sensor, never span a gap (a lost BLE packet), and are
    numbered ``seq = 0, 1, ...`` per sensor; they are returned in upload order (by ``t0_ms``, interleaving the
    sensors as a phone would). Without ``with_timestamps`` the samples are implied at ``t0_ms + i * 1000 / fs``,
    which is exact for the simulator's nominal-rate timestamps.
    """
    if batch_size < 1:
        raise ValueError("batch_size must be >= 1")
    started = started_at or datetime(2026, 11, 21, 9, 30, tzinfo=UTC)
    cfg = sim.config
    csid = client_session_id or str(uuid.uuid5(
        uuid.NAMESPACE_URL, f"gaitmon-sim:{cfg.pattern}:{cfg.seed}:{cfg.fs_hz}:{sim.duration_s:.3f}:"
                            f"{started.isoformat()}"))
    create = {
        "patient_id": patient_id,
        "client_session_id": csid,
        "started_at": started.isoformat(),
        "activity": sim.activity,
        "sensors": [{"sensor_id": s.sensor_id, "leg": s.leg, "segment": s.segment, "sample_rate_hz": s.fs_hz,
                     "gyro_unit": s.gyro_unit, "acc_unit": s.acc_unit} for s in sim.streams],
    }
    gyro_dec = 3 if sim.streams and sim.streams[0].gyro_unit == "deg/s" else 6
    acc_dec = 4 if sim.streams and sim.streams[0].acc_unit == "m/s2" else 6
    batches: list[dict] = []
    for s in sim.streams:
        t_ms = np.asarray(s.t_s) * 1000.0
        period_ms = 1000.0 / s.fs_hz
        breaks = np.flatnonzero(np.diff(t_ms) > 1.5 * period_ms) + 1
        seq = 0
        for run in np.split(np.arange(len(t_ms)), breaks):
            for i0 in range(0, len(run), batch_size):
                idx = run[i0:i0 + batch_size]
                body: dict[str, Any] = {
                    "sensor_id": s.sensor_id, "seq": seq, "t0_ms": round(float(t_ms[idx[0]]), 3),
                    "gyro": np.round(s.gyr[idx], gyro_dec).tolist(),
                    "acc": np.round(s.acc[idx], acc_dec).tolist(),
                }
                if with_timestamps:
                    body["timestamps_ms"] = np.round(t_ms[idx], 3).tolist()
                batches.append(body)
                seq += 1
    batches.sort(key=lambda b: (b["t0_ms"], b["sensor_id"]))
    return create, batches


def arrange_batches(batches: list[dict], shuffle: bool = False, duplicate_fraction: float = 0.0,
                    seed: int = 0) -> list[dict]:
    """Upload order: optionally shuffled, with a fraction of batches sent twice (later in the order)."""
    rng = random.Random(seed)
    out = list(batches)
    if duplicate_fraction > 0:
        dups = rng.sample(range(len(batches)), k=min(len(batches), round(duplicate_fraction * len(batches))))
        for i in dups:
            out.insert(rng.randint(i + 1, len(out)), batches[i])
    if shuffle:
        rng.shuffle(out)
    return out


def truth_summary(sim: SimSession) -> dict:
    """Per-leg ground truth the server's results can be compared with (steady strides only)."""
    out: dict = {}
    for leg, tr in sim.truth.items():
        st = [s for s in tr.strides if s.steady]
        out[leg] = {
            "n_strides": len(tr.strides),
            "n_steady_strides": len(st),
            "peak_swing_flexion_deg_median": float(np.median([s.peak_swing_flexion_deg for s in st])) if st else None,
            "rom_deg_median": float(np.median([s.rom_deg for s in st])) if st else None,
            "min_flexion_deg_median": float(np.median([s.min_flexion_deg for s in st])) if st else None,
            "strides": [{"t_start_s": round(s.t_start_s, 4), "t_end_s": round(s.t_end_s, 4),
                         "t_toe_off_s": round(s.t_toe_off_s, 4),
                         "peak_swing_flexion_deg": round(s.peak_swing_flexion_deg, 3),
                         "min_flexion_deg": round(s.min_flexion_deg, 3), "rom_deg": round(s.rom_deg, 3),
                         "stance_flexion_deg": round(s.stance_flexion_deg, 3), "steady": s.steady}
                        for s in tr.strides],
        }
    return out


# ---------------------------------------------------------------------------------------------------------------
# HTTP (through gaitmon.client: retries, gzip, typed answers)


def upload(client: Client, create: dict, batches: list[dict], concurrency: int = 4,
           progress: Callable[[str], None] = _log) -> str:
    """Create the session, send every batch (gzip'd), complete it; returns the session id."""
    sess = client.create_session(**create)
    progress(f"session {sess.id} ({sess.status}); uploading {len(batches)} batches")
    step = max(1, len(batches) // 10)
    stored = duplicates = 0
    with ThreadPoolExecutor(max_workers=max(1, concurrency)) as pool:
        for done, res in enumerate(pool.map(lambda b: client.upload_batch(sess.id, b), batches), start=1):
            duplicates += res.duplicate
            stored += not res.duplicate
            if done % step == 0 or done == len(batches):
                progress(f"  {done}/{len(batches)} batches sent")
    progress(f"batches: {stored} stored, {duplicates} duplicates acknowledged")
    client.complete_session(sess.id)
    progress(f"session {sess.id} completed; processing in the background")
    return sess.id


def print_result(client: Client, sess: Session, truth: dict | None) -> None:
    """Print the processed session's summary and its strides against the simulator's truth."""
    print(f"session {sess.id}: {sess.status}" + (f" ({sess.error})" if sess.error else "")
          + f", algorithm {sess.algorithm_version}")
    if sess.status != "done":
        return
    print("| leg | strides | true strides | peak swing median (deg) | true | ROM median (deg) | true | estimators |")
    print("|---|---|---|---|---|---|---|---|")
    for leg in ("left", "right"):
        strides = client.get_strides(sess.id, leg=leg).strides
        tr = (truth or {}).get(leg)
        if not strides and not tr:
            continue
        peaks = [s.peak_swing_flexion_deg for s in strides if s.peak_swing_flexion_deg is not None]
        roms = [s.rom_deg for s in strides if s.rom_deg is not None]
        est: dict[str, int] = {}
        for s in strides:
            est[s.estimator] = est.get(s.estimator, 0) + 1

        def fmt(x: float | None) -> str:
            return "-" if x is None else f"{x:.1f}"
        print(f"| {leg} | {len(strides)} | {tr['n_strides'] if tr else '-'} | "
              f"{fmt(float(np.median(peaks)) if peaks else None)} | "
              f"{fmt(tr['peak_swing_flexion_deg_median'] if tr else None)} | "
              f"{fmt(float(np.median(roms)) if roms else None)} | {fmt(tr['rom_deg_median'] if tr else None)} | "
              f"{', '.join(f'{k}: {v}' for k, v in sorted(est.items()))} |")


# ---------------------------------------------------------------------------------------------------------------
# CLI


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``gaitmon simulate`` to the command line."""
    p = subparsers.add_parser("simulate", help="simulate a session: write it as JSON or upload it to a server",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pattern", choices=PATTERNS, default="normal")
    p.add_argument("--minutes", type=float, default=2.0, help="approximate session length")
    p.add_argument("--fs", type=float, default=100.0, help="sample rate, Hz (50-200)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--legs", choices=["both", "left", "right"], default="both")
    p.add_argument("--mounting", choices=["random", "aligned"], default="random")
    p.add_argument("--gyro-unit", choices=["deg/s", "rad/s"], default="deg/s")
    p.add_argument("--acc-unit", choices=["m/s2", "g"], default="m/s2")
    p.add_argument("--packet-loss", type=float, default=None, help="probability of losing a BLE packet")
    p.add_argument("--batch-size", type=int, default=50, help="samples per sensor per upload batch")
    p.add_argument("--no-timestamps", action="store_true", help="omit timestamps_ms (implied by t0_ms and rate)")
    p.add_argument("--started-at", default=None, help="ISO 8601 session start (default: now)")
    p.add_argument("--client-session-id", default=None)
    p.add_argument("--out", default=None, help="write {session, batches, truth} JSON here ('-' for stdout)")
    p.add_argument("--from-file", default=None, help="upload a file written by --out instead of simulating")
    p.add_argument("--server", default=None, help="base URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--token", default=None, help="device or clinician bearer token")
    p.add_argument("--patient-id", default=None)
    p.add_argument("--shuffle", action="store_true", help="upload batches in random order")
    p.add_argument("--duplicate-fraction", type=float, default=0.0, help="fraction of batches sent twice")
    p.add_argument("--concurrency", type=int, default=4, help="parallel batch uploads")
    p.add_argument("--wait", action="store_true", help="poll until processed and print the stride summary")
    p.add_argument("--wait-timeout", type=float, default=600.0)
    p.set_defaults(func=run)
    return p


def _build(args: argparse.Namespace) -> tuple[dict, list[dict], dict | None]:
    if args.from_file:
        doc = json.loads(Path(args.from_file).read_text())
        create = doc["session"]
        if args.patient_id:
            create["patient_id"] = args.patient_id
        return create, doc["batches"], doc.get("truth")
    cfg = SimConfig(pattern=args.pattern, fs_hz=args.fs, seed=args.seed, duration_s=args.minutes * 60.0,
                    legs=("left", "right") if args.legs == "both" else (args.legs,), mounting=args.mounting,
                    gyro_unit=args.gyro_unit, acc_unit=args.acc_unit)
    if args.packet_loss is not None:
        cfg.packet_loss = args.packet_loss
    t0 = time.perf_counter()
    sim = simulate_session(cfg)
    started = datetime.fromisoformat(args.started_at) if args.started_at else datetime.now(UTC).replace(microsecond=0)
    if started.tzinfo is None:
        started = started.replace(tzinfo=UTC)
    create, batches = session_to_requests(sim, args.batch_size, patient_id=args.patient_id or "PATIENT_ID",
                                          started_at=started, client_session_id=args.client_session_id,
                                          with_timestamps=not args.no_timestamps)
    truth = truth_summary(sim)
    _log(f"simulated {args.pattern}, {sim.duration_s:.0f} s at {args.fs:g} Hz (seed {args.seed}) in "
         f"{time.perf_counter() - t0:.1f} s: {sum(len(s.t_s) for s in sim.streams)} samples, {len(batches)} batches, "
         + ", ".join(f"{leg}: {v['n_strides']} strides" for leg, v in truth.items()))
    return create, batches, truth


def run(args: argparse.Namespace) -> int:
    """``gaitmon simulate``: upload a simulated session to a running service and report the result."""
    if not args.out and not args.server:
        _log("error: give --out FILE and/or --server URL (with --token and --patient-id)")
        return 2
    if args.server and not (args.token and (args.patient_id or args.from_file)):
        _log("error: --server needs --token and --patient-id")
        return 2
    if not 0.0 <= args.duplicate_fraction <= 1.0:
        _log("error: --duplicate-fraction must be within 0..1")
        return 2
    try:
        create, batches, truth = _build(args)
    except (ValueError, OSError, KeyError) as exc:
        _log(f"error: {exc}")
        return 2
    if args.out:
        text = json.dumps({"session": create, "batches": batches, "truth": truth}, separators=(",", ":"))
        if args.out == "-":
            sys.stdout.write(text + "\n")
        else:
            Path(args.out).write_text(text)
            _log(f"wrote {args.out} ({len(text) / 1e6:.1f} MB)")
    if not args.server:
        return 0
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request drowns the progress lines
    order = arrange_batches(batches, args.shuffle, args.duplicate_fraction, seed=args.seed)
    try:
        with Client(args.server, args.token, timeout_s=60.0) as client:
            sid = upload(client, create, order, concurrency=args.concurrency)
            if args.wait:
                sess = client.wait_for_processing(sid, timeout_s=args.wait_timeout)
                print_result(client, sess, truth)
                return 0 if sess.status == "done" else 1
            print(sid)
    except (ApiError, TimeoutError, httpx.HTTPError) as exc:
        _log(f"error: {exc}")
        return 1
    return 0
