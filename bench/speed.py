"""Processing speed of ``pipeline.session.process_session`` on one core.

    python -m bench.speed [--runs 7] [--minutes 10] [--fs 100] [--estimator auto] [--profile-top 15]
    python -m bench.speed --lengths 10m,1h,12h [--pool 1] [--chunk-s 1800]

A 10-minute, two-leg, 100 Hz simulated session (normal walking bouts with standing between) is processed ``--runs``
times; median and best wall time are printed with the 0.3 s target, then the pipeline functions with the largest
cumulative time in one profiled run (cProfile; profiling itself slows the run down).

``--lengths``: per length, a session is written to float32/float64 files in a temporary directory, 10-minute
simulated pieces one after the other: by default the same piece repeated (one body, one mounting, lever arms and
clock offset per sensor for the whole day, so every length holds the same data per minute); ``--pool N`` cycles N
seeds, whose bodies and lever arms differ (a change of subject every 10 minutes, harder for the fits). Each length
is processed in its own subprocess by gaitmon (:func:`pipeline.long_sessions.process_source`, reading the files
window by window) and by the plain reference
(:mod:`bench.reference_go_seel`, whole arrays in memory), so that CPU time (of the processing call) and peak RSS
(the child's ``VmHWM``, imports included; :func:`peak_rss_mb`) belong to one run each.
"""

from __future__ import annotations

import os

# Single-threaded BLAS/OpenMP, set before numpy is imported: the target is per core.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import cProfile  # noqa: E402
import json  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.params import WALKING  # noqa: E402

TARGET_S = 0.3


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def time_runs(fn, runs: int) -> np.ndarray:
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return np.array(out)


def profile_rows(fn, top: int) -> list[tuple[str, int, float, float]]:
    """(function, calls, own time, cumulative time) of the pipeline's own functions, by cumulative time."""
    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    stats = pstats.Stats(prof)
    rows = []
    for (path, line, name), (_, ncalls, tottime, cumtime, _) in stats.stats.items():  # type: ignore[attr-defined]
        norm = path.replace(os.sep, "/")
        if "/pipeline/" not in norm or "/site-packages/" in norm:
            continue
        module = norm[norm.rindex("/pipeline/") + 1:].removesuffix(".py").replace("/", ".")
        rows.append((f"{module}.{name}:{line}", int(ncalls), float(tottime), float(cumtime)))
    rows.sort(key=lambda r: -r[3])
    return rows[:top]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.speed", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--fs", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--estimator", default="auto")
    ap.add_argument("--profile-top", type=int, default=15, help="0: no profile")
    ap.add_argument("--lengths", help="session lengths for the scaling table, e.g. 10m,1h,12h")
    ap.add_argument("--pool", type=int, default=1, help="--lengths: distinct 10-minute pieces, repeated")
    ap.add_argument("--repeat", type=int, default=3, help="--lengths: runs per length and program (median CPU)")
    ap.add_argument("--chunk-s", type=float, help="--lengths: gaitmon's chunk length [s] (default: the parameter tree)")
    ap.add_argument("--child", choices=("gaitmon", "reference"), help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(run_child(args.child, Path(args.data), args.estimator, args.chunk_s)))
        return 0
    if args.lengths:
        return scaling(args)
    # imported here, not at the top: a --child reference run must not load gaitmon's pipeline (and its compiled
    # kernels, ~140 MB), which would count in the reference's peak RSS
    from pipeline.session import process_session
    from pipeline.simulate import SimConfig, simulate_session

    t0 = time.perf_counter()
    sim = simulate_session(SimConfig(pattern="normal", fs_hz=args.fs, seed=args.seed,
                                     duration_s=args.minutes * 60.0, activities=("standing",),
                                     bout_strides=40))
    n_samples = sum(len(s.t_s) for s in sim.streams)
    n_true = sum(len(t.strides) for t in sim.truth.values())
    _log(f"simulated {sim.duration_s:.0f} s, {len(sim.streams)} sensors, {n_samples} samples in "
         f"{time.perf_counter() - t0:.1f} s")

    def work():
        return process_session(sim.streams, activity=sim.activity, estimator=args.estimator)

    res = work()  # warm-up: imports, caches
    n_strides = sum(len(lr.strides) for lr in res.legs.values())
    times = time_runs(work, args.runs)
    med, best = float(np.median(times)), float(times.min())
    miss = " ✗" if med > TARGET_S else ""
    print(f"## Processing speed (`process_session`, estimator `{args.estimator}`, one core)\n")
    print(f"Session: {sim.duration_s / 60:.1f} min, both legs, {args.fs:g} Hz, {len(sim.streams)} sensors, "
          f"{n_samples} samples; {n_strides} strides detected ({n_true} simulated).\n")
    print("| runs | median (s) | best (s) | target (s) | samples/s (median) |")
    print("|---|---|---|---|---|")
    print(f"| {args.runs} | {med:.3f}{miss} | {best:.3f} | <= {TARGET_S:g} | {n_samples / med:,.0f} |")
    if args.profile_top > 0:
        rows = profile_rows(work, args.profile_top)
        print("\nLargest cumulative times inside `pipeline` (one cProfiled run; profiling adds overhead):\n")
        print("| function | calls | own (s) | cumulative (s) |")
        print("|---|---|---|---|")
        for name, calls, own, cum in rows:
            print(f"| `{name}` | {calls} | {own:.3f} | {cum:.3f} |")
    return 0



PIECE_S = 600.0


def parse_length(text: str) -> float:
    """``10m``, ``1h``, ``90s`` -> seconds."""
    unit = {"s": 1.0, "m": 60.0, "h": 3600.0}[text[-1]]
    return float(text[:-1]) * unit


def write_session(path: Path, length_s: float, fs: float, seed: int, pool: int) -> dict:
    """A session of ``length_s`` written piece by piece (never whole in memory): per sensor ``<id>.t`` float64,
    ``<id>.gyr`` / ``<id>.acc`` float32 (N, 3). Pieces are simulated with aligned mountings and no clock error,
    then given one random mounting and timestamp offset per sensor, so the session looks like one recording."""
    from pipeline.simulate import SimConfig, simulate_session  # not at the top: see main()

    rng = np.random.default_rng([seed, 99])
    piece_s = min(PIECE_S, length_s)
    n_pieces = max(1, int(np.ceil(length_s / piece_s - 1e-9)))
    meta: dict = {"length_s": n_pieces * piece_s, "pieces": n_pieces, "sensors": {}}
    rot: dict[str, np.ndarray] = {}
    offset: dict[str, float] = {}
    sims: dict[int, list] = {}
    for k in range(n_pieces):
        if k % pool not in sims:
            sims[k % pool] = simulate_session(SimConfig(
                pattern="normal", fs_hz=fs, seed=seed + k % pool, duration_s=piece_s, activities=("standing",),
                bout_strides=40, mounting="aligned", sync_offset_ms=0.0, clock_drift_ppm=0.0)).streams
        for s in sims[k % pool]:
            if s.sensor_id not in rot:
                q, r = np.linalg.qr(rng.standard_normal((3, 3)))
                rot[s.sensor_id] = q * np.sign(np.diag(r)) * np.sign(np.linalg.det(q * np.sign(np.diag(r))))
                offset[s.sensor_id] = float(rng.normal(0.0, 0.005))
                meta["sensors"][s.sensor_id] = {"leg": s.leg, "segment": s.segment, "fs_hz": s.fs_hz,
                                                "gyro_unit": s.gyro_unit, "acc_unit": s.acc_unit, "n": 0}
            r = rot[s.sensor_id]
            t = s.t_s + k * piece_s + offset[s.sensor_id]
            t = t[t > k * piece_s]  # strictly after the previous piece's last sample
            m = t.size
            with open(path / f"{s.sensor_id}.t", "ab") as f:
                f.write(t.astype(np.float64).tobytes())
            for name, x in (("gyr", s.gyr), ("acc", s.acc)):
                with open(path / f"{s.sensor_id}.{name}", "ab") as f:
                    f.write((x[-m:] @ r).astype(np.float32).tobytes())
            meta["sensors"][s.sensor_id]["n"] += m
        _log(f"  piece {k + 1}/{n_pieces} written")
    (path / "meta.json").write_text(json.dumps(meta))
    return meta


class FileSource:
    """:class:`pipeline.long_sessions.StreamSource` over the files of :func:`write_session`: each window maps the
    files, copies its samples and unmaps them, so only one window is ever resident."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.meta = json.loads((path / "meta.json").read_text())

    def _t(self, sid: str) -> np.memmap:
        return np.memmap(self.path / f"{sid}.t", dtype=np.float64, mode="r")

    def span_s(self) -> tuple[float, float]:
        """First and last sample time [s] over all sensors."""
        ends = []
        for sid in self.meta["sensors"]:
            t = self._t(sid)
            ends.append((float(t[0]), float(t[-1])))
            del t
        return min(a for a, _ in ends), max(b for _, b in ends)

    def window(self, t0_s: float, t1_s: float) -> list:
        """Every sensor's samples with ``t0_s <= t < t1_s``."""
        from pipeline.types import RawSensorStream

        out = []
        for sid, m in self.meta["sensors"].items():
            tm = self._t(sid)
            a, b = (int(i) for i in np.searchsorted(tm, [t0_s, t1_s]))
            t = np.array(tm[a:b])
            del tm
            if b <= a:
                continue
            arrays = []
            for name in ("gyr", "acc"):
                mm = np.memmap(self.path / f"{sid}.{name}", dtype=np.float32, mode="r", offset=12 * a,
                               shape=(b - a, 3))
                arrays.append(np.array(mm, dtype=np.float64))
                del mm
            out.append(RawSensorStream(sensor_id=sid, leg=m["leg"], segment=m["segment"], fs_hz=m["fs_hz"], t_s=t,
                                       gyr=arrays[0], acc=arrays[1], gyro_unit=m["gyro_unit"],
                                       acc_unit=m["acc_unit"]))
        return out


def run_child(which: str, path: Path, estimator: str, chunk_s: float | None = None) -> dict:
    """One processing run in this process: CPU seconds of the call, peak RSS [MB], strides."""
    src = FileSource(path)
    if which == "gaitmon":
        import dataclasses

        from pipeline.long_sessions import process_source

        chunking = WALKING.long_sessions if chunk_s is None else dataclasses.replace(WALKING.long_sessions,
                                                                                      chunk_s=chunk_s)
        t0 = time.process_time()
        res = process_source(src, activity="walking", estimator=estimator, chunking=chunking)
        cpu = time.process_time() - t0
        n = sum(len(lr.strides) for lr in res.legs.values())
    else:
        from bench.reference_go_seel import process

        t0 = time.process_time()
        n = sum(process(src.window(-np.inf, np.inf)).values())  # the plain reference holds the whole session
        cpu = time.process_time() - t0
    return {"cpu_s": cpu, "rss_mb": peak_rss_mb(), "strides": n}


def peak_rss_mb() -> float:
    """This process's peak resident set [MB]: ``VmHWM`` of its own address space where Linux has it. ``ru_maxrss``
    is not used there: after fork and exec it starts from the parent's resident set at the fork (the kernel
    carries the old address space's high-water mark over exec), so every child would report at least the
    benchmark parent's size."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _child(which: str, path: Path, estimator: str, chunk_s: float | None) -> dict:
    cmd = [sys.executable, "-m", "bench.speed", "--child", which, "--data", str(path), "--estimator", estimator]
    if chunk_s is not None:
        cmd += ["--chunk-s", str(chunk_s)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        return {"error": (out.stderr.strip().splitlines() or [f"exit {out.returncode}"])[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _repeated(which: str, path: Path, estimator: str, chunk_s: float | None, repeat: int) -> dict:
    """``repeat`` child runs: median CPU time (a shared machine's noise), largest peak RSS."""
    runs = [_child(which, path, estimator, chunk_s) for _ in range(max(1, repeat))]
    bad = [r for r in runs if "error" in r]
    if bad:
        return bad[0]
    return {"cpu_s": float(np.median([r["cpu_s"] for r in runs])), "rss_mb": max(r["rss_mb"] for r in runs),
            "strides": runs[0]["strides"], "runs": len(runs)}


def scaling(args: argparse.Namespace) -> int:
    """The per-length table: gaitmon and the reference on the same files, one subprocess per run."""
    rows = []
    for text in args.lengths.split(","):
        with tempfile.TemporaryDirectory(prefix="gaitmon-speed-") as tmp:
            _log(f"{text}: writing the session")
            meta = write_session(Path(tmp), parse_length(text), args.fs, args.seed, args.pool)
            minutes = meta["length_s"] / 60.0
            runs = {w: _repeated(w, Path(tmp), args.estimator, args.chunk_s, args.repeat)
                    for w in ("gaitmon", "reference")}
        _log(f"{text}: {runs}")
        rows.append((text, minutes, meta["pieces"], runs))
    load = os.getloadavg()
    print(f"## Processing speed by session length (estimator `{args.estimator}`, one core each, "
          f"load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f})\n")
    chunk = args.chunk_s if args.chunk_s is not None else WALKING.long_sessions.chunk_s
    print(f"Two legs, {args.fs:g} Hz, 4 sensors; sessions made of 10-minute simulated pieces ({args.pool} distinct "
          f"seed(s), repeated); gaitmon chunk {chunk:g} s. gaitmon reads the files window by window "
          "(`pipeline.long_sessions`); the reference "
          "(`bench/reference_go_seel.py`: Seel 2014 axes by Gauss-Newton on every sample, Allseits 2018 GO) "
          "holds the whole session in memory. CPU s: the processing call, median of "
          f"{args.repeat} subprocess runs; peak RSS: the largest of those runs.\n")
    print("| length | gaitmon CPU s | gaitmon CPU s/min | gaitmon peak RSS MB | reference CPU s | "
          "reference CPU s/min | reference peak RSS MB | CPU gaitmon/reference | strides gaitmon / reference |")
    print("|---|---|---|---|---|---|---|---|---|")
    base = None
    for text, minutes, _, runs in rows:
        g, r = runs["gaitmon"], runs["reference"]
        if "error" in g or "error" in r:
            print(f"| {text} | {g.get('error', '')} | | | {r.get('error', '')} | | | | |")
            continue
        per_min = g["cpu_s"] / minutes
        base = per_min if base is None else base
        print(f"| {text} | {g['cpu_s']:.3f} | {per_min:.4f} | {g['rss_mb']:.0f} | {r['cpu_s']:.3f} | "
              f"{r['cpu_s'] / minutes:.4f} | {r['rss_mb']:.0f} | {g['cpu_s'] / r['cpu_s']:.2f} | "
              f"{g['strides']} / {r['strides']} |")
    if base is not None and len(rows) > 1:
        last = rows[-1]
        if "error" not in last[3]["gaitmon"]:
            ratio = last[3]["gaitmon"]["cpu_s"] / last[1] / base
            print(f"\ngaitmon CPU per minute at {last[0]} / at {rows[0][0]}: {ratio:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
