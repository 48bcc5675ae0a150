"""Processing speed of ``pipeline.session.process_session`` on one core.

    python -m bench.speed [--runs 7] [--minutes 10] [--fs 100] [--estimator auto] [--profile-top 15]

A 10-minute, two-leg, 100 Hz simulated session (normal walking bouts with standing between) is processed ``--runs``
times; median and best wall time are printed with the 0.3 s target, then the pipeline functions with the largest
cumulative time in one profiled run (cProfile; profiling itself slows the run down).
"""

from __future__ import annotations

import os

# Single-threaded BLAS/OpenMP, set before numpy is imported: the target is per core.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.session import process_session  # noqa: E402
from pipeline.simulate import SimConfig, simulate_session  # noqa: E402

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
    args = ap.parse_args(argv)

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


if __name__ == "__main__":
    raise SystemExit(main())
