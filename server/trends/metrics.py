"""The trend metrics: where each comes from, which values are plausible and what change is clinically meaningful.

Quality gate: a stride counts only when ``Stride.quality >= MIN_QUALITY`` (the pipeline's 0..1 score; 0.5 means
"at least half of its checks passed") AND its value lies inside the metric's plausibility limits. Everything else is
counted as excluded (``low_quality`` or ``implausible``) and reported with the statistics, never silently dropped.

Minimal detectable change (MDC), the ``change.mdc`` of the trends response:

- ``peak_swing_flexion_deg``, ``rom_deg``: 5 deg. Allseits et al. 2018 (papers/allseits2018-gyroscope-only.txt,
  Results 3.2 and Discussion) use "the 5 deg error accepted as a clinical standard for minimum detectable change"
  (their ref. 17, Wilken et al., Gait Posture 2012); their GO estimator's RMSE against three references was 5-7 deg.
- ``min_flexion_deg``, ``stance_flexion_deg``: 5 deg, the same angular measurement threshold (same sensor, same
  estimator, same reference study); a smaller change cannot be told apart from measurement error.
- ``stride_time_s``: 0.10 s, about 9 % of a typical 1.1 s stride. The papers give no MDC for timing; this is an
  engineering choice: gait events come from the shank gyroscope at ~100 Hz, so 0.10 s is ten samples, well above
  event-timing jitter, and of the order of the ~10 % coefficient of variation Allseits et al. 2018 report for their
  per-stride Bland-Altman comparison (Results 3.2).
- ``swing_time_s``: 0.05 s (swing is ~40 % of the stride; the same ~10 % relative threshold).
- ``cadence_steps_per_min``: 10 steps/min, the stride-time MDC propagated through cadence = 120 / T at T = 1.1 s
  (|d cadence| = 120 * 0.1 / 1.1**2 ~ 10).
- ``stance_pct``: 3 percentage points (~5 % of a typical 60 % stance; toe-off detection error of a few samples).
- ``strides_per_day``: relative, 30 % of the baseline (day-to-day variation of free-living activity counts is
  commonly 20-30 %; a smaller change is ordinary week-to-week fluctuation). Engineering choice, documented here.

Plausibility limits are physiological bounds, wide on purpose (they remove estimator failures, not patients): knee
flexion/extension range is about 142.5 deg (McGrath et al. 2018, papers/mcgrath2018-pca-knee-axis.txt, section 1),
so peak swing flexion and ROM outside 0-140 deg cannot be a real walking stride; hyperextension beyond -20 deg or a
minimum flexion above 60 deg neither. Stride times 0.4-4 s cover running to very slow pathological walking.
"""

from __future__ import annotations

from dataclasses import dataclass
from operator import attrgetter
from typing import Any, Literal

import numpy as np

MIN_QUALITY = 0.5
# Sessions with fewer included strides are too noisy to be one point of the session-level trend.
MIN_STRIDES_PER_SESSION = 5

Direction = Literal["higher", "lower", "none"]


@dataclass(frozen=True)
class Metric:
    """A trend metric: its source column, unit, plausibility limits and MDC."""

    name: str
    unit: str  # human unit, also UCUM where the two agree
    ucum: str  # UCUM code for FHIR valueQuantity.code
    column: str | None  # Stride column it derives from; None for count metrics
    lo: float
    hi: float
    mdc: float
    mdc_relative: bool = False  # mdc is a fraction of the baseline instead of an absolute value
    better: Direction = "higher"  # which direction is clinical improvement
    title: str = ""

    def values(self, raw: np.ndarray) -> np.ndarray:
        """The metric from its Stride column (cadence: two steps per stride, per minute)."""
        if self.name == "cadence_steps_per_min":
            with np.errstate(divide="ignore", invalid="ignore"):
                return 120.0 / raw
        return raw

    def plausible(self, values: np.ndarray) -> np.ndarray:
        return np.isfinite(values) & (values >= self.lo) & (values <= self.hi)


METRICS: dict[str, Metric] = {m.name: m for m in [
    Metric("peak_swing_flexion_deg", "deg", "deg", "peak_swing_flexion_deg", 0.0, 140.0, 5.0,
           title="Peak swing knee flexion"),
    Metric("rom_deg", "deg", "deg", "rom_deg", 0.0, 140.0, 5.0, title="Knee flexion range of motion per stride"),
    # Lower minimum flexion = fuller extension = better (an extension deficit shrinking).
    Metric("min_flexion_deg", "deg", "deg", "min_flexion_deg", -20.0, 60.0, 5.0, better="lower",
           title="Minimum knee flexion per stride"),
    Metric("stance_flexion_deg", "deg", "deg", "stance_flexion_deg", -20.0, 90.0, 5.0, better="none",
           title="Knee flexion during loading response"),
    Metric("stride_time_s", "s", "s", "duration_s", 0.4, 4.0, 0.10, better="lower", title="Stride time"),
    Metric("swing_time_s", "s", "s", "swing_time_s", 0.1, 2.0, 0.05, better="none", title="Swing time"),
    Metric("stance_pct", "%", "%", "stance_pct", 30.0, 90.0, 3.0, better="none", title="Stance phase"),
    Metric("cadence_steps_per_min", "steps/min", "/min", "duration_s", 30.0, 300.0, 10.0,
           title="Cadence"),
    Metric("strides_per_day", "strides/day", "/d", None, 0.0, float("inf"), 0.30, mdc_relative=True,
           title="Trustworthy strides per day"),
]}

# Metrics stored per session-leg as value arrays (everything that comes from a stride column).
STRIDE_METRICS: tuple[str, ...] = tuple(name for name, m in METRICS.items() if m.column is not None)


def stride_exclusions(rows: list[Any]) -> list[list[str]]:
    """Per stride, why it does not count in the trends (empty: it counts): ``quality<0.5`` (and nothing else), or
    ``implausible:<metric>`` for each metric whose value is outside its plausible range. The pages (through the
    results service) and the CSV export say why a stride is excluded from this one rule.

    ``rows``: anything with ``quality`` and the metric columns as attributes (the results service's stride rows).
    The rule of :func:`server.trends.summaries.summarise_leg`, evaluated on whole columns with the same
    :class:`Metric` methods (per-stride calls cost ~60 us each, too slow for a long session)."""
    if not rows:
        return []
    metrics = [(name, metric) for name, metric in METRICS.items() if metric.column is not None]
    # One attribute fetch per stride for every column at once (None becomes NaN in a float array).
    table = np.array([attrgetter("quality", *(m.column for _, m in metrics))(r) for r in rows], dtype=np.float64)
    table = table.reshape(len(rows), len(metrics) + 1)
    out: list[list[str]] = [[] for _ in rows]
    low = ~(table[:, 0] >= MIN_QUALITY)
    for i in np.flatnonzero(low):
        out[i].append(f"quality<{MIN_QUALITY:g}")
    for j, (name, metric) in enumerate(metrics, start=1):
        with np.errstate(divide="ignore", invalid="ignore"):
            bad = ~metric.plausible(metric.values(table[:, j])) & ~low
        for i in np.flatnonzero(bad):
            out[i].append(f"implausible:{name}")
    return out
