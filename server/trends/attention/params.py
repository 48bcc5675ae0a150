"""The thresholds of the attention flags, with named presets a clinic chooses from (echoed in every response).

Every number here is a clinic's choice, not a law of nature; ``rules`` in the response says which were used.
False-alarm rates measured with the defaults on simulated stable patients: ``python -m bench.cohort`` (README).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from server.enums import StrideActivity

# Functional goal per metric: a plateau at or above it is a patient who has arrived, not one who is stuck.
# Unimpaired walking reaches ~60-65 deg of peak swing flexion and ~60 deg of sagittal knee ROM (Perry & Burnfield,
# Gait Analysis, 2nd ed. 2010, ch. 7); the default sits a few degrees below, the size of the gyroscope-only
# estimator's error (5-7 deg RMSE, Allseits et al. 2018), so a patient walking normally is never called stalled.
GOALS: dict[str, float] = {"peak_swing_flexion_deg": 57.0, "rom_deg": 57.0}


# The pipeline's session-to-session scatter of session means (residual sd about a patient's own trend line, deg):
# pooled over the 72 walking patients of the cohort benchmark's tune seeds (``python -m bench.cohort --split tune``;
# dev seeds: 2.65 / 2.94). It is the prior of the moderated slope test (``sd_prior_df``; rules.moderated).
SESSION_SD_PRIOR: dict[str, float] = {"rom_deg": 2.7, "peak_swing_flexion_deg": 3.0}


@dataclass(frozen=True)
class AttentionParams:
    """The thresholds of the flags. Windows end now; ``window_days`` is the sensor window, the trend window is
    twice as long (the same 28 days by default the baseline-vs-latest comparison spans)."""

    preset: str = "default"
    metric: str = "peak_swing_flexion_deg"
    activity: str = StrideActivity.walking  # declining/improving/stalled judge strides of this activity only
    window_days: float = 14.0
    # declining / improving: one-sided t-test of the OLS slope of session means AND a fitted change beyond the MDC
    alpha: float = 0.005
    level_free_test: bool = True  # absolute angles: test on the level-free companion (rules.LEVEL_FREE_COMPANION)
    # Weight of SESSION_SD_PRIOR in residual degrees of freedom (0: the plain t-test on the patient's own scatter).
    # The tune cohort's per-patient variances spread exactly as sampling noise on 6 df would (Smyth's estimate of
    # d0 is unbounded); 10 keeps most of the patient's own scatter in play, for patients noisier than simulated.
    sd_prior_df: int = 10
    min_trend_sessions: int = 4
    min_trend_span_days: float = 7.0
    # stalled: after enough exposure, the one-sided upper confidence bound of the improvement slope below the MDC
    # per stalled_margin_days (the patient would not show a detectable gain between two comparison windows),
    # the latest level below the goal
    stalled_weeks: int = 4  # the plateau window
    stalled_min_span_days: float = 21.0
    stalled_min_sessions: int = 6
    stalled_margin_days: float = 14.0
    stalled_confidence: float = 0.95
    stalled_goal: float | None = None  # None: GOALS of the metric (no goal known: never stalled)
    # silent: no session for silent_days, or for silent_missed_sessions prescribed intervals when a schedule is set
    silent_days: float = 3.0
    silent_missed_sessions: float = 2.0
    # sensor_trouble: only data that cost strides or quality, judged after enough exposure
    min_strides_for_rates: int = 100  # expected strides of a leg in the window before any rate is judged
    min_session_strides: int = 10  # expected strides of one session before a stopped sensor is judged
    max_lost_rate: float = 0.4  # strides the leg should have given but did not (the other leg gave them)
    max_low_quality_rate: float = 0.25  # strides the pipeline could not vouch for (saturation, drift, ...)
    max_fallback_rate: float = 0.3  # strides from the activity's fallback estimator
    max_implausible_rate: float = 0.1  # quality-passing strides with an impossible knee angle
    min_coverage: float = 0.8  # a sensor delivering data for less of the session has stopped (or started late)
    min_lost_strides: int = 5  # ... and is trouble only when that cost at least this many strides
    max_failed_sessions: int = 1  # more failed processing runs in the window than this is trouble

    def goal(self) -> float | None:
        """The stalled goal of the metric (the clinic's, else the metric's default)."""
        return self.stalled_goal if self.stalled_goal is not None else GOALS.get(self.metric)

    def as_dict(self) -> dict[str, Any]:
        """The parameters as JSON (the goal resolved)."""
        return {**asdict(self), "stalled_goal": self.goal(), "activity": str(self.activity)}


PRESETS: dict[str, AttentionParams] = {
    "default": AttentionParams(),
    # More flags, earlier: a clinic that prefers a phone call too many to a decline noticed late.
    "sensitive": AttentionParams(preset="sensitive", alpha=0.02, silent_days=2.0, silent_missed_sessions=1.5,
                                 max_lost_rate=0.3, max_low_quality_rate=0.2, max_fallback_rate=0.2,
                                 max_implausible_rate=0.05),
    # Fewer flags: a large caseload where only unmistakable changes should reach the clinician.
    "conservative": AttentionParams(preset="conservative", alpha=0.001, silent_days=5.0, silent_missed_sessions=3.0,
                                    max_lost_rate=0.5, max_low_quality_rate=0.35, max_fallback_rate=0.4,
                                    max_implausible_rate=0.15),
}


def params_for(preset: str = "default", **overrides: Any) -> AttentionParams:
    """A preset with some fields overridden (``None`` overrides are ignored). Raises KeyError for an unknown
    preset."""
    return replace(PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None})
