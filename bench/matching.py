"""Scoring a pipeline result against simulator ground truth: stride matching and agreement statistics.

Agreement follows Bland and Altman (Lancet 1986): bias = mean difference, 95 % limits of agreement = bias +- 1.96 SD.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.params import WALKING
from pipeline.simulate import LegTruth, SimSession, TruthStride
from pipeline.types import LegResult, StrideMetrics

# the pipeline's own bridging limit (periodic fill from the neighbouring strides): longer gaps are masked and no
# stride may span them
MAX_BRIDGE_S = WALKING.prepare.periodic_bridge_s
TREND_QUALITY = 0.5  # server.trends.metrics.MIN_QUALITY: the strides a clinician's trend is built on
QUALITY_BINS = ((0.0, 0.5), (0.5, 0.8), (0.8, 1.0001))  # below the trend threshold, trend, vouched for

PLAUSIBLE_DEG = (-15.0, 160.0)  # a knee angle outside this cannot be true (issue targets)
MATCH_TOL_S = 0.15  # both heel strikes of a detected stride within this of the true ones (and < 25 % of a stride)
OUTSIDE_GAIT_MARGIN_S = 1.0  # gait initiation and termination around a bout's first and last heel strike


@dataclass
class LegScore:
    """Raw material of one leg of one case; pooled over cases before any statistic is taken."""

    n_expected: int = 0  # steady true strides with complete data
    n_steady: int = 0  # steady true strides (incl. those lost to data gaps)
    tp: int = 0
    fp: int = 0
    peak_err: list[float] = field(default_factory=list)
    rom_err: list[float] = field(default_factory=list)
    min_err: list[float] = field(default_factory=list)
    hs_err_s: list[float] = field(default_factory=list)
    to_err_s: list[float] = field(default_factory=list)
    sq_err_sum: float = 0.0
    n_samples: int = 0
    stride_sq_err_sum: float = 0.0  # inside expected true strides only
    n_stride_samples: int = 0
    outside_sq_err_sum: float = 0.0  # farther than OUTSIDE_GAIT_MARGIN_S from every walking bout
    n_outside_samples: int = 0
    n_non_gait: int = 0  # detected strides overlapping a non-gait movement (sitting, jumps, stairs...)
    n_implausible: int = 0  # finite angle samples outside PLAUSIBLE_DEG
    # every matched stride (steady or not, across gaps or not): (quality, peak error [deg]); unmatched: quality
    quality_err: list[tuple[float, float]] = field(default_factory=list)
    fp_quality: list[float] = field(default_factory=list)
    peak_err_trend: list[float] = field(default_factory=list)  # hits that enter trends (quality >= TREND_QUALITY)

    def add(self, other: LegScore) -> None:
        for name in ("n_expected", "n_steady", "tp", "fp", "sq_err_sum", "n_samples", "stride_sq_err_sum",
                     "n_stride_samples", "outside_sq_err_sum", "n_outside_samples", "n_non_gait", "n_implausible"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for name in ("peak_err", "rom_err", "min_err", "hs_err_s", "to_err_s", "quality_err", "fp_quality",
                     "peak_err_trend"):
            getattr(self, name).extend(getattr(other, name))


def data_gaps(sim: SimSession, leg: str) -> list[tuple[float, float]]:
    """Intervals without data on either sensor of the leg that the pipeline cannot bridge."""
    out = []
    for s in sim.streams:
        if s.leg != leg:
            continue
        dt = np.diff(s.t_s)
        idx = np.flatnonzero((dt > WALKING.prepare.gap_factor / s.fs_hz) & (dt > MAX_BRIDGE_S))
        out += [(float(s.t_s[i]), float(s.t_s[i + 1])) for i in idx]
    return out


def _overlaps(a: float, b: float, gaps: list[tuple[float, float]], margin: float = 0.05) -> bool:
    return any(g0 < b + margin and g1 > a - margin for g0, g1 in gaps)


def match_strides(detected: list[StrideMetrics], truth: list[TruthStride]) -> list[tuple[int, int]]:
    """One-to-one pairs (detected index, true index) whose start and end heel strikes both agree within the
    tolerance; the closest pairs are taken first."""
    if not detected or not truth:
        return []
    ts = np.array([t.t_start_s for t in truth])
    te = np.array([t.t_end_s for t in truth])
    tol = np.minimum(MATCH_TOL_S, 0.25 * (te - ts))
    cands = []
    for i, d in enumerate(detected):
        ds, de = np.abs(ts - d.t_start_s), np.abs(te - d.t_end_s)
        for j in np.flatnonzero((ds <= tol) & (de <= tol)):
            cands.append((float(ds[j] + de[j]), i, int(j)))
    cands.sort()
    used_d: set[int] = set()
    used_t: set[int] = set()
    pairs = []
    for _, i, j in cands:
        if i not in used_d and j not in used_t:
            used_d.add(i)
            used_t.add(j)
            pairs.append((i, j))
    return pairs


def score_leg(res: LegResult | None, truth: LegTruth, gaps: list[tuple[float, float]],
              non_gait: list[tuple[str, float, float]] | None = None) -> LegScore:
    """Match one leg's strides to the truth and collect errors. ``non_gait``: (kind, start, end) intervals of
    movements that are not gait (``SimSession.info["non_gait_s"]``); a detected stride overlapping one counts in
    ``n_non_gait``."""
    sc = LegScore()
    expected = [s.steady and not _overlaps(s.t_start_s, s.t_end_s, gaps) for s in truth.strides]
    sc.n_expected = int(sum(expected))
    sc.n_steady = sum(1 for s in truth.strides if s.steady)
    if res is None:
        return sc
    pairs = match_strides(res.strides, truth.strides)
    matched_d = {i for i, _ in pairs}
    for i, j in pairs:
        sc.quality_err.append((res.strides[i].quality,
                               res.strides[i].peak_swing_flexion_deg - truth.strides[j].peak_swing_flexion_deg))
        if not expected[j]:
            continue  # gait initiation/termination or across a gap: neither a hit nor a false alarm
        d, t = res.strides[i], truth.strides[j]
        sc.tp += 1
        sc.peak_err.append(d.peak_swing_flexion_deg - t.peak_swing_flexion_deg)
        if d.quality >= TREND_QUALITY:
            sc.peak_err_trend.append(d.peak_swing_flexion_deg - t.peak_swing_flexion_deg)
        sc.rom_err.append(d.rom_deg - t.rom_deg)
        sc.min_err.append(d.min_flexion_deg - t.min_flexion_deg)
        sc.hs_err_s.append(d.t_start_s - t.t_start_s)
        sc.to_err_s.append(d.t_toe_off_s - t.t_toe_off_s)
    sc.fp = len(res.strides) - len(matched_d)
    sc.fp_quality = [d.quality for i, d in enumerate(res.strides) if i not in matched_d]
    sc.n_non_gait = sum(1 for d in res.strides
                        if any(a < d.t_end_s and d.t_start_s < b for _, a, b in (non_gait or [])))
    angle = np.asarray(res.angle_deg, dtype=float)
    t_s = np.asarray(res.t_s, dtype=float)
    ok = np.isfinite(angle)
    if ok.any():
        err = angle[ok] - truth.angle_at(t_s[ok])
        sc.sq_err_sum = float(np.sum(err**2))
        sc.n_samples = int(ok.sum())
        sc.n_implausible = int(np.sum((angle[ok] < PLAUSIBLE_DEG[0]) | (angle[ok] > PLAUSIBLE_DEG[1])))
        inside = np.zeros(t_s.size, dtype=bool)
        for s, exp in zip(truth.strides, expected, strict=True):
            if exp:
                inside[np.searchsorted(t_s, s.t_start_s):np.searchsorted(t_s, s.t_end_s, side="right")] = True
        walking = np.zeros(t_s.size, dtype=bool)
        for b0, b1 in truth.bouts_s:
            walking[np.searchsorted(t_s, b0 - OUTSIDE_GAIT_MARGIN_S):
                    np.searchsorted(t_s, b1 + OUTSIDE_GAIT_MARGIN_S, side="right")] = True
        out = ~walking & ok
        if out.any():
            e = angle[out] - truth.angle_at(t_s[out])
            sc.outside_sq_err_sum = float(np.sum(e**2))
            sc.n_outside_samples = int(out.sum())
        sel = inside & ok
        if sel.any():
            e = angle[sel] - truth.angle_at(t_s[sel])
            sc.stride_sq_err_sum = float(np.sum(e**2))
            sc.n_stride_samples = int(sel.sum())
    return sc


def quality_bins(sc: LegScore) -> list[dict[str, float]]:
    """Per :data:`QUALITY_BINS` bin: matched strides, |peak error| p50/p95 [deg], share within 3 deg, false
    strides."""
    q = np.array([x for x, _ in sc.quality_err], dtype=float)
    e = np.abs(np.array([y for _, y in sc.quality_err], dtype=float))
    fq = np.asarray(sc.fp_quality, dtype=float)
    out = []
    for lo, hi in QUALITY_BINS:
        sel = e[(q >= lo) & (q < hi)]
        nan = float("nan")
        out.append({"lo": lo, "hi": min(hi, 1.0), "n": float(sel.size),
                    "p50": float(np.percentile(sel, 50)) if sel.size else nan,
                    "p95": float(np.percentile(sel, 95)) if sel.size else nan,
                    "within3": float(np.mean(sel <= 3.0)) if sel.size else nan,
                    "fp": float(np.sum((fq >= lo) & (fq < hi)))})
    return out


def bland_altman(err: list[float] | np.ndarray) -> tuple[float, float, float]:
    """(bias, lower, upper) 95 % limits of agreement; NaN when fewer than two values."""
    e = np.asarray(err, dtype=float)
    if e.size < 2:
        return float("nan"), float("nan"), float("nan")
    bias, sd = float(e.mean()), float(e.std(ddof=1))
    return bias, bias - 1.96 * sd, bias + 1.96 * sd


def summarise(sc: LegScore) -> dict[str, float]:
    """The figures of one table row."""
    peak = bland_altman(sc.peak_err)
    rom = bland_altman(sc.rom_err)
    trend = bland_altman(sc.peak_err_trend)
    nan = float("nan")
    return {
        "n_true": float(sc.n_expected),
        "recall": sc.tp / sc.n_expected if sc.n_expected else nan,
        "precision": sc.tp / (sc.tp + sc.fp) if sc.tp + sc.fp else nan,
        "coverage": sc.tp / sc.n_steady if sc.n_steady else nan,
        # the coverage the data allows: steady strides without a gap longer than the bridge limit
        "coverage_max": sc.n_expected / sc.n_steady if sc.n_steady else nan,
        "peak_bias": peak[0], "peak_lo": peak[1], "peak_hi": peak[2],
        "rom_bias": rom[0], "rom_lo": rom[1], "rom_hi": rom[2],
        "trend_share": len(sc.peak_err_trend) / sc.tp if sc.tp else nan,
        "peak_trend_bias": trend[0], "peak_trend_lo": trend[1], "peak_trend_hi": trend[2],
        "rmse": float(np.sqrt(sc.sq_err_sum / sc.n_samples)) if sc.n_samples else nan,
        "rmse_strides": float(np.sqrt(sc.stride_sq_err_sum / sc.n_stride_samples)) if sc.n_stride_samples else nan,
        "rmse_outside": float(np.sqrt(sc.outside_sq_err_sum / sc.n_outside_samples)) if sc.n_outside_samples
        else nan,
        "non_gait_strides": float(sc.n_non_gait),
        "implausible_share": sc.n_implausible / sc.n_samples if sc.n_samples else nan,
        "hs_ms": 1000 * float(np.mean(np.abs(sc.hs_err_s))) if sc.hs_err_s else nan,
        "to_ms": 1000 * float(np.mean(np.abs(sc.to_err_s))) if sc.to_err_s else nan,
    }
