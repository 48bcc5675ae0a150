"""Long sessions (a day of continuous monitoring) processed in overlapping time chunks.

A session is read from a :class:`StreamSource` one window at a time: chunk k owns ``[edge_k, edge_k+1)`` and is
processed from the samples of ``[edge_k - overlap, edge_k+1 + overlap)`` by :func:`pipeline.session.process_session`,
so memory is bounded by one chunk and time is linear in the length. A session no longer than one chunk is one
block: exactly :func:`process_session`'s output.

Why a whole pipeline run per chunk (joint axes and all) rather than one axis fit for the day:

- GO needs nothing beyond a stride: the zero-angle update once per stride (Allseits et al. 2018, Sect. 2.2) resets
  the integral, so a stride's angle depends on the samples of that stride and its filter margins only;
- the axis fit of Seel et al. 2014 (Eq. 2) needs only a few hundred samples of varied motion
  (``AxesParams.max_fit_samples`` already bounds it per run); a chunk of walking holds far more. Refitting per chunk
  follows a sensor that slips or is put on again during the day, which one fit for the day cannot, and each chunk
  is processed exactly like a short session, so the accuracy figures of short sessions carry over;
- the alternative (a bounded sample spread over the day, fitted once) needs a first pass over every window and
  still costs one fit; per chunk the fit is a fixed cost per chunk, i.e. linear.

Strides are kept once: each chunk contributes the strides that start in its owned part (from ``dedupe_s`` before
it, for a heel strike found a few milliseconds earlier by the next chunk), and a stride starting within
``dedupe_s`` of the last one kept is the same stride seen by two chunks.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from pipeline import ALGORITHM_VERSION
from pipeline.estimators import get_estimator
from pipeline.params import LongSessionParams, PipelineParams, preset
from pipeline.session import process_session
from pipeline.signal_utils import merged_intervals
from pipeline.types import (
    KneeCalibration,
    LegDiagnostics,
    LegResult,
    MountingCheck,
    RawSensorStream,
    SessionResult,
    StrideMetrics,
)


@runtime_checkable
class StreamSource(Protocol):
    """A session's sensor streams, read one time window at a time (a file, a database, arrays)."""

    def span_s(self) -> tuple[float, float]:
        """First and last sample time [s] over all sensors."""
        ...

    def window(self, t0_s: float, t1_s: float) -> list[RawSensorStream]:
        """Every sensor's samples with ``t0_s <= t < t1_s`` (sensors without any sample there may be left out)."""
        ...


class ArraySource:
    """A :class:`StreamSource` over whole per-sensor arrays: in memory, or ``np.memmap`` so that only the windows
    asked for are read (``t_s`` float64, sorted; ``gyr``/``acc`` (N, 3) of any float type, returned as float64)."""

    def __init__(self, streams: Sequence[RawSensorStream]) -> None:
        self.streams = list(streams)

    def span_s(self) -> tuple[float, float]:
        """First and last sample time [s] over all sensors."""
        ts = [s.t_s for s in self.streams if len(s.t_s)]
        if not ts:
            return 0.0, 0.0
        return float(min(t[0] for t in ts)), float(max(t[-1] for t in ts))

    def window(self, t0_s: float, t1_s: float) -> list[RawSensorStream]:
        """Every sensor's samples with ``t0_s <= t < t1_s``; sensors without any are left out."""
        out = []
        for s in self.streams:
            a, b = np.searchsorted(s.t_s, [t0_s, t1_s], side="left")
            if b <= a:
                continue
            out.append(dataclasses.replace(
                s, t_s=np.asarray(s.t_s[a:b], dtype=np.float64), gyr=np.asarray(s.gyr[a:b], dtype=np.float64),
                acc=np.asarray(s.acc[a:b], dtype=np.float64)))
        return out


def chunk_edges(t0_s: float, t1_s: float, params: LongSessionParams) -> np.ndarray:
    """Edges of the owned parts: equal chunks of at most ``chunk_s`` covering ``[t0_s, t1_s]``."""
    n = max(1, math.ceil((t1_s - t0_s) / params.chunk_s))
    return np.linspace(t0_s, t1_s, n + 1)


def process_source(source: StreamSource, activity: str = "walking", estimator: str = "auto",
                   params: PipelineParams | None = None, calibration: Mapping[str, KneeCalibration] | None = None,
                   chunking: LongSessionParams | None = None) -> SessionResult:
    """:func:`pipeline.session.process_session` of the whole source, chunk by chunk when it spans more than
    ``chunking.chunk_s`` (None: ``params.long_sessions``, the activity's preset without ``params``).

    Chunked results have the same type: strides from every chunk (each once, renumbered), one trace per leg on one
    grid (at most ``trace_max_fs_hz`` beyond ``full_rate_trace_s``), the leg diagnostics of the chunk with most
    strides (counts over the session). A chunk the pipeline cannot use (no samples, one segment missing) is a
    warning, not a failure.
    """
    if estimator != "auto":
        get_estimator(estimator)  # fail early on an unknown name, not as a warning per chunk
    lp = chunking if chunking is not None else (params if params is not None else preset(activity)).long_sessions
    t0, t1 = source.span_s()
    if t1 - t0 <= lp.chunk_s:
        return process_session(source.window(-math.inf, math.inf), activity=activity, estimator=estimator,
                               params=params, calibration=calibration)
    edges = chunk_edges(t0, t1, lp)
    merged = _Merged(t0, t1, lp, n_chunks=edges.size - 1)
    for k in range(edges.size - 1):
        lo, hi = float(edges[k]), float(edges[k + 1])
        own = (-math.inf if k == 0 else lo, math.inf if k == edges.size - 2 else hi)
        streams = source.window(lo - lp.overlap_s, hi + lp.overlap_s)
        try:
            res = process_session(streams, activity=activity, estimator=estimator, params=params,
                                  calibration=calibration)
        except ValueError as exc:
            merged.skipped(lo, hi, f"not processed: {exc}")
            continue
        finally:
            del streams
        merged.add(lo, hi, own, res)
        del res  # the chunk's full-rate arrays; only its strides and trace samples are kept
    return merged.result(activity)


def _renumbered(s: StrideMetrics, index: int) -> StrideMetrics:
    """``dataclasses.replace(s, index=index)`` without its keyword round trip through ``__init__`` (a day holds tens
    of thousands of strides): StrideMetrics is a plain frozen dataclass (no ``__post_init__``, no slots), so copying
    its fields is the same object."""
    out = object.__new__(StrideMetrics)
    out.__dict__.update(s.__dict__)
    out.__dict__["index"] = index
    return out


def _clock(t_s: float) -> str:
    t = max(0, int(round(t_s)))
    return f"{t // 3600:02d}:{t // 60 % 60:02d}:{t % 60:02d}"


class _LegTrace:
    """One leg's decimated trace on the grid ``g0 + j * dt`` of the whole session."""

    def __init__(self, g0: float, t1: float, fs_hz: float, max_fs_hz: float) -> None:
        self.step = max(1, int(round(fs_hz / max_fs_hz)))
        self.fs_hz = fs_hz / self.step
        self.g0 = g0
        self.n = int(math.floor((t1 - g0) * self.fs_hz)) + 1
        self.angle = np.full(self.n, np.nan)
        self.codes = np.zeros(self.n, dtype=np.uint8)
        self.names: list[str] = [""]

    def add(self, lr: LegResult, own: tuple[float, float]) -> None:
        """The chunk's samples nearest to the grid points of its owned part (none farther than half a sample)."""
        t = lr.t_s
        if t.size == 0:
            return
        lo = max(0, math.ceil((max(own[0], t[0]) - self.g0) * self.fs_hz - 1e-9))
        hi = min(self.n, math.ceil((min(own[1], t[-1] + 1e-9) - self.g0) * self.fs_hz - 1e-9))
        if hi <= lo:
            return
        tg = self.g0 + np.arange(lo, hi) / self.fs_hz
        i = np.clip(np.searchsorted(t, tg), 1, t.size - 1)
        i -= (tg - t[i - 1]) < (t[i] - tg)
        ok = np.abs(t[i] - tg) <= 0.5 / lr.fs_hz + 1e-9
        self.angle[lo:hi][ok] = lr.angle_deg[i[ok]]
        est = np.asarray(lr.estimator)[i[ok]]
        # a handful of distinct names: one comparison pass per name instead of np.unique's sort of every string
        codes = np.zeros(est.size, dtype=np.uint8)
        todo = np.ones(est.size, dtype=bool)
        while todo.any():
            name = str(est[int(np.argmax(todo))])
            hit = est == name
            codes[hit] = self._code(name)
            todo &= ~hit
        self.codes[lo:hi][ok] = codes

    def _code(self, name: str) -> int:
        if name not in self.names:
            self.names.append(name)
        return self.names.index(name)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t_s, angle_deg, estimator)`` with "" where there is no estimate."""
        self.codes[~np.isfinite(self.angle)] = 0
        return self.g0 + np.arange(self.n) / self.fs_hz, self.angle, np.array(self.names)[self.codes]


@dataclasses.dataclass
class _Leg:
    strides: list[StrideMetrics] = dataclasses.field(default_factory=list)
    gaps: list[tuple[float, float]] = dataclasses.field(default_factory=list)
    trace: _LegTrace | None = None
    best: LegResult | None = None  # the chunk result with most strides: its diagnostics describe the leg
    best_n: int = -1
    activities: Counter = dataclasses.field(default_factory=Counter)
    bouts: int = 0
    bridged: int = 0
    masked: int = 0
    clock_disagreement: bool = False  # in any chunk
    gait_strides: int = 0
    lowered: int = 0
    withheld: str | None = None  # the chunks' trace_withheld when every chunk withheld the leg's trace
    shown: bool = False  # some chunk showed the leg's trace
    mounting: MountingCheck | None = None  # the first chunk's check that found a mounting change
    not_worn: list[tuple[float, float]] = dataclasses.field(default_factory=list)  # every chunk's, overlaps merged
    handled: list[tuple[float, float]] = dataclasses.field(default_factory=list)  # ditto

    def count(self, d: LegDiagnostics) -> None:
        """Add one chunk's counts and flags."""
        self.bouts += d.bouts
        self.bridged += d.bridged_gaps
        self.masked += d.masked_implausible_samples
        self.clock_disagreement |= d.clock_disagreement
        self.gait_strides += d.gait_strides
        self.lowered += d.lowered_strides
        if d.trace_withheld is None:
            self.shown = True
        else:
            self.withheld = d.trace_withheld
        if d.mounting is not None and d.mounting.changed and (self.mounting is None or not self.mounting.changed):
            self.mounting = d.mounting  # a chunk whose sensor was turned speaks for the leg
        self.not_worn = merged_intervals([*self.not_worn, *d.not_worn_s])
        self.handled = merged_intervals([*self.handled, *d.handled_s])


class _Merged:
    """Per-leg strides, gaps, trace and diagnostics gathered chunk by chunk."""

    def __init__(self, t0: float, t1: float, params: LongSessionParams, n_chunks: int) -> None:
        self.t0, self.t1, self.params, self.n_chunks = t0, t1, params, n_chunks
        self.legs: dict[str, _Leg] = {}
        self.warnings: dict[str, list[tuple[float, float]]] = {}
        self.version = ALGORITHM_VERSION
        self.chunks: list[tuple[float, float, set[str]]] = []  # owned part and the legs it gave

    def note(self, lo: float, hi: float, msg: str) -> None:
        self.warnings.setdefault(msg, []).append((lo, hi))

    def skipped(self, lo: float, hi: float, msg: str) -> None:
        self.note(lo, hi, msg)
        self.chunks.append((lo, hi, set()))

    def add(self, lo: float, hi: float, own: tuple[float, float], res: SessionResult) -> None:
        self.version = res.algorithm_version
        self.chunks.append((lo, hi, set(res.legs)))
        for w in res.warnings:
            self.note(lo, hi, w)
        for name, lr in res.legs.items():
            leg = self.legs.setdefault(name, _Leg())
            first_ok = own[0] - self.params.dedupe_s
            for s in lr.strides:
                if not first_ok <= s.t_start_s < own[1]:
                    continue
                if leg.strides and s.t_start_s - leg.strides[-1].t_start_s < self.params.dedupe_s:
                    continue  # the same stride, already kept from the previous chunk
                leg.strides.append(s)
            for a, b in lr.gaps_s:
                a, b = max(a, own[0]), min(b, own[1])
                if b <= a:
                    continue
                if leg.gaps and a <= leg.gaps[-1][1]:
                    leg.gaps[-1] = (leg.gaps[-1][0], max(b, leg.gaps[-1][1]))
                else:
                    leg.gaps.append((a, b))
            if leg.trace is None:
                full = self.t1 - self.t0 <= self.params.full_rate_trace_s
                leg.trace = _LegTrace(self.t0, self.t1, lr.fs_hz, lr.fs_hz if full else self.params.trace_max_fs_hz)
            leg.trace.add(lr, own)
            n_own = sum(1 for s in lr.strides if own[0] <= s.t_start_s < own[1])
            leg.activities[lr.activity] += n_own + 1e-6  # a chunk without strides still says what the leg was
            if n_own > leg.best_n:
                leg.best = dataclasses.replace(lr, t_s=lr.t_s[:0], angle_deg=lr.angle_deg[:0],
                                               estimator=np.asarray(lr.estimator)[:0], strides=[])
                leg.best_n = n_own
            if lr.diagnostics is not None:
                leg.count(lr.diagnostics)

    def _warnings(self) -> list[str]:
        for lo, hi, legs in self.chunks:
            for leg in sorted(set(self.legs) - legs):
                self.note(lo, hi, f"{leg} leg: no result (no usable samples of both segments)")
        out = []
        for msg, where in self.warnings.items():
            if len(where) == 1:
                out.append(f"{_clock(where[0][0])}-{_clock(where[0][1])}: {msg}")
            else:
                out.append(f"{msg} (in {len(where)} of {self.n_chunks} chunks)")
        return out

    def result(self, activity: str) -> SessionResult:
        legs: dict[str, LegResult] = {}
        for name in sorted(self.legs):
            leg = self.legs[name]
            assert leg.best is not None and leg.trace is not None
            strides = [_renumbered(s, i) for i, s in enumerate(leg.strides)]
            t_s, angle, est = leg.trace.arrays()
            diag = leg.best.diagnostics
            if diag is not None:
                diag = dataclasses.replace(diag, n_strides=len(strides),
                                           n_fallback=sum(1 for s in strides if s.fallback), bouts=leg.bouts,
                                           bridged_gaps=leg.bridged, masked_implausible_samples=leg.masked,
                                           clock_disagreement=leg.clock_disagreement,
                                           gait_strides=leg.gait_strides, lowered_strides=leg.lowered,
                                           trace_withheld=None if leg.shown else leg.withheld,
                                           mounting=leg.mounting if leg.mounting is not None else diag.mounting,
                                           not_worn_s=tuple(leg.not_worn), handled_s=tuple(leg.handled))
            legs[name] = dataclasses.replace(
                leg.best, fs_hz=leg.trace.fs_hz, t_s=t_s, angle_deg=angle, estimator=est, strides=strides,
                gaps_s=leg.gaps, walking_s=float(sum(s.duration_s for s in strides)),
                activity=leg.activities.most_common(1)[0][0], diagnostics=diag)
        return SessionResult(algorithm_version=self.version, activity=activity, legs=legs,
                             warnings=self._warnings())
