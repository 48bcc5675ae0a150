"""Codes of the API in the words a physiotherapist reads on the pages (statuses, quality reasons, flags)."""

from __future__ import annotations

from datetime import datetime
from typing import Any
from zoneinfo import ZoneInfo

from server.trends.metrics import METRICS
from server.utc import as_utc

STATUS = {
    "receiving": "Receiving data from the phone",
    "queued": "Waiting to be processed",
    "processing": "Being processed",
    "done": "Processed",
    "failed": "Processing failed",
}

# Per-stride quality reasons (pipeline.reasons lists every code; each lowers the stride's 0..1 quality score).
REASONS = {
    "assumed_level": "level assumed: no calibration of the standing knee angle recorded",
    "go_level": "running without a moment of quiet standing: the angle's level is unknown",
    "peak_in_gap": "the peak of the swing fell in a data gap",
    "long_gap": "a long data gap was filled from the neighbouring strides",
    "event_in_gap": "a heel strike or toe-off fell in a data gap",
    "bout_edge": "first or last stride of a walk",
    "turning": "a stride of a turn, not of straight walking",
    "no_absolute_reference": "no still moment to anchor the angle (thigh/shank never quiet)",
    "few_quiet_samples": "few still moments to anchor the angle",
    "no_go_estimate": "gyroscope-only estimate incomplete",
    "no_zero_crossing": "no zero-velocity point to reset drift",
    "drift": "angle drift too large",
    "saturation": "a sensor reading hit its full-scale limit",
    "bridged_gap": "a short data gap was bridged",
    "go_cf_mismatch": "the two estimators disagree",
    "level_wander": "running: the angle's level strayed in this stride",
    "leg_mismatch": "most of this leg's strides failed the agreement of the two estimators: none is trusted",
    "cf_fallback": "complementary filter used instead of the gyroscope-only estimator",
    "clock_disagreement": "the thigh and shank sensors' clocks ran apart: the angle's timing cannot be trusted",
    "side_in_doubt": "the left and right sensor labels look swapped: this stride may belong to the other knee",
    "mounting_changed": "a sensor was turned or re-fastened on the leg during the session: the angle cannot be "
                        "trusted",
    "sensors_handled": "the sensors were taken off or put back during the session, and too little was recorded "
                       "around this stride to check how they sat: the angle cannot be trusted",
}

ESTIMATORS = {
    "auto": "automatic choice (what the stored results use)",
    "go": "gyroscope-only with zero-angle updates (Allseits 2018)",
    "cf": "complementary filter (Seel 2014 / Rhudy 2024)",
    "kf": "linear Kalman filter (Rhudy 2024)",
    "ekf": "extended Kalman filter (Rhudy 2024)",
}

METRIC_SHORT = {
    "peak_swing_flexion_deg": "Peak knee flexion in swing",
    "rom_deg": "Knee range of motion per stride",
    "min_flexion_deg": "Minimum knee flexion in stance (extension deficit)",
    "strides_per_day": "Trustworthy strides per day",
}

UNIT = {"deg": "\u00b0", "strides/day": " strides/day", "s": " s", "%": " %", "steps/min": " steps/min"}

DIRECTION = {
    "improved": "improved beyond measurement error",
    "declined": "got worse beyond measurement error",
    "changed": "changed beyond measurement error",
    "unchanged": "no change beyond measurement error",
    None: "not enough data to judge",
}


def unit(metric: str) -> str:
    """The metric's unit as printed after a value."""
    return UNIT.get(METRICS[metric].unit, " " + METRICS[metric].unit)


def value(x: float | None, metric: str, nd: int = 1) -> str:
    """A metric value with its unit, or an em dash."""
    if x is None:
        return "\u2014"
    return f"{x:.{nd}f}{unit(metric)}".replace("-", "\u2212")


def reason(code: str) -> str:
    """A quality reason code in words."""
    return REASONS.get(code, code.replace("_", " "))


def exclusion(code: str) -> str:
    """An exclusion of :func:`server.trends.metrics.stride_exclusions` in words."""
    if code.startswith("quality<"):
        return f"quality below {code.split('<', 1)[1]}"
    if code.startswith("implausible:"):
        name = code.split(":", 1)[1]
        m = METRICS.get(name)
        return f"implausible {m.title.lower() if m else name}"
    return code


def local_time(dt: datetime | None, tz: ZoneInfo, *, with_date: bool = True) -> str:
    """A stored (UTC) time in the patient's zone, e.g. 'Tue 1 Dec 2026, 09:30'."""
    if dt is None:
        return "\u2014"
    t = as_utc(dt).astimezone(tz)
    return f"{t:%a} {t.day} {t:%b %Y}, {t:%H:%M}" if with_date else f"{t:%H:%M}"


def local_date(dt: datetime | str | None, tz: ZoneInfo) -> str:
    """A date in the patient's time zone, or a dash."""
    if dt is None:
        return "\u2014"
    t = as_utc(datetime.fromisoformat(dt) if isinstance(dt, str) else dt).astimezone(tz)
    return f"{t:%a} {t.day} {t:%b %Y}"


def flag(f: dict[str, Any], tz: ZoneInfo) -> str:
    """One attention flag (server.trends.attention) as a sentence: the flag's own reason, which states the numbers
    behind it; a silent patient's last session in the patient's time zone."""
    if f["kind"] == "silent" and f.get("last_session_at"):
        # whole days, as a clinician counts them: 9.5 days without a session is "9 days", not "10"
        days = int(f.get("days_without_data") or 0)
        return f"No session for {days} days (last on {local_date(f['last_session_at'], tz)})."
    return str(f.get("reason") or f["kind"].replace("_", " "))


SEVERITY = {3: "Act now", 2: "Check", 1: "Review", 0: "Good news"}
