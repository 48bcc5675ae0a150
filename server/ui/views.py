"""What each page shows: data from the services (through :mod:`server.ui.data` where the pages need it adapted)
turned into rows, sentences and SVG charts."""

from __future__ import annotations

import math
from datetime import date, datetime, timedelta
from typing import Any

from sqlalchemy.orm import Session as DbSession
from sqlalchemy.orm import sessionmaker

from server.auth.service import Principal
from server.patients import service as patient_service
from server.patients.models import Patient
from server.results import service as results_service
from server.results.service import CYCLE_POINTS, Cycle, TraceWindow
from server.sessions.models import Session
from server.trends import service as trend_service
from server.trends.metrics import METRICS, stride_exclusions
from server.trends.timeutil import zone
from server.ui import data, plots, words
from server.ui.plots import AFFECTED, OTHER, Axis, Band, HBand, Series
from server.utc import as_utc

CALENDAR_DAYS = 182
SESSIONS_PER_PAGE = 20
STRIDES_SHOWN = 300
# The metrics of the patient page, in the order a physiotherapist reads them, and those of the patient list.
TREND_METRICS = ("peak_swing_flexion_deg", "rom_deg", "min_flexion_deg", "strides_per_day")
OVERVIEW_METRICS = ("peak_swing_flexion_deg", "rom_deg")


def leg_roles(patient: Patient, legs: list[str]) -> tuple[str, str]:
    """(reference leg, other leg): the affected leg when recorded, else the leg with most data, else left."""
    ref = patient.affected_leg or (legs[0] if legs else "left")
    return ref, "right" if ref == "left" else "left"


def leg_name(patient: Patient, leg: str) -> str:
    """The leg in words, marked when it is the affected one."""
    return f"{leg.capitalize()} leg" + (" (affected)" if patient.affected_leg == leg else "")


# --- My patients ---------------------------------------------------------------------------------------------

def patients_page(db: DbSession, principal: Principal, *, search: str, page: int, per_page: int = 25) -> dict:
    """Template context of the patient list."""
    listing = patient_service.patient_page(db, principal, search=search, offset=(page - 1) * per_page,
                                           limit=per_page)
    rows = []
    latest_all = trend_service.latest_session_means(db, [p.id for p in listing.items], OVERVIEW_METRICS)
    for p in listing.items:
        tz = zone(p.timezone)
        comp = data.completeness(db, p, days=30)
        latest = latest_all.get(p.id, {})
        legs = []
        for leg in ("left", "right"):
            if leg in latest:
                v = latest[leg]
                legs.append({"leg": leg_name(p, leg),
                             "peak": words.value(v.get("peak_swing_flexion_deg", {}).get("mean"),
                                                 "peak_swing_flexion_deg"),
                             "rom": words.value(v.get("rom_deg", {}).get("mean"), "rom_deg")})
        last = comp["last_session_at"]
        rows.append({"id": p.id, "label": p.display_name or p.external_id or p.id, "external_id": p.external_id,
                     "last_session": words.local_date(last, tz) if last else "no session yet",
                     "days_with_data": comp["days_with_data"], "legs": legs, "timezone": tz.key})
    att = data.attention(db, principal)
    attention = []
    for item in att["items"]:
        pt = item["patient"]
        p_tz = zone(_patient_tz(db, pt["id"]))
        attention.append({"id": pt["id"], "label": pt["display_name"] or pt["external_id"] or pt["id"],
                          "external_id": pt["external_id"], "severity": words.SEVERITY[item["severity"]],
                          "level": item["severity"], "flags": [words.flag(f, p_tz) for f in item["flags"]]})
    n_pages = max(1, math.ceil(listing.total / per_page))
    return {"rows": rows, "attention": attention, "n_flagged": att["n_flagged"], "total": listing.total,
            "page": page, "n_pages": n_pages, "search": search}


def _patient_tz(db: DbSession, patient_id: str) -> str:
    p = db.get(Patient, patient_id)
    return p.timezone if p is not None else "UTC"


# --- Patient page --------------------------------------------------------------------------------------------

def _bucket_day(b: dict[str, Any]) -> date:
    return date.fromisoformat(b["start"][:10])  # bucket starts are local ISO date-times of the patient


def trend_chart(patient: Patient, metric: str, per_leg: dict[str, dict[str, Any]], ref: str, bucket: str,
                first: date, last: date) -> str:
    """SVG trend chart of one metric: the affected leg against the other, baseline +- MDC band."""
    m = METRICS[metric]
    x = plots.date_axis(f"Local date ({patient.timezone})", first, last)
    series, bands, hbands, ys = [], [], [], []
    for leg, color, dash in ((ref, AFFECTED, None), ("left" if ref == "right" else "right", OTHER, "6 4")):
        tr = per_leg.get(leg)
        if not tr or not tr["buckets"]:
            continue
        xs = [float((_bucket_day(b) - first).days) for b in tr["buckets"]]
        means = [b["mean"] for b in tr["buckets"]]
        ys += means
        if m.column is not None:
            p10 = [b["p10"] for b in tr["buckets"]]
            p90 = [b["p90"] for b in tr["buckets"]]
            ys += p10 + p90
            if leg == ref:
                bands.append(Band(f"{leg.capitalize()} leg: middle 80 % of strides", xs, p10, p90, color, 0.12))
        series.append(Series(f"{leg_name(patient, leg)}: {'daily' if bucket == 'day' else 'weekly'} mean", xs,
                             means, color, dash, 2.4 if leg == ref else 1.8, markers=len(xs) <= 60))
    ch = (per_leg.get(ref) or {}).get("change") or {}
    if ch.get("baseline") is not None and ch.get("mdc") is not None:
        lo, hi = ch["baseline"] - ch["mdc"], ch["baseline"] + ch["mdc"]
        hbands.append(HBand(f"{ref.capitalize()} leg baseline \u00b1 minimal detectable change ({ch['mdc']:.3g}"
                            f"{words.unit(metric).strip() if metric != 'strides_per_day' else ''})", lo, hi))
        ys += [lo, hi]
    unit_label = {"deg": "degrees (\u00b0)", "strides/day": "strides per day"}.get(m.unit, m.unit)
    y = plots.numeric_axis(unit_label, ys, lo=0.0 if metric == "strides_per_day" else None)
    title = words.METRIC_SHORT.get(metric, m.title)
    desc = "; ".join(_trend_sentence(patient, metric, leg, per_leg[leg]) for leg in per_leg if per_leg[leg])
    return plots.chart(title=title, desc=desc or "no data", x=x, y=y, series=series, bands=bands, hbands=hbands,
                       subtitle=_subtitle(metric))


def _subtitle(metric: str) -> str:
    return {"peak_swing_flexion_deg": "Higher is better. Each point pools the trustworthy strides of that period.",
            "rom_deg": "Higher is better.",
            "min_flexion_deg": "Lower is better: 0\u00b0 is a fully straight knee at its straightest in stance.",
            "strides_per_day": "How much the patient walked with the sensors on."}.get(metric, "")


def _trend_sentence(patient: Patient, metric: str, leg: str, tr: dict[str, Any]) -> str:
    t = tr["trend"]
    if t["slope_per_week"] is None:
        return f"{leg_name(patient, leg)}: not enough sessions for a trend"
    return f"{leg_name(patient, leg)}: {_slope_text(metric, t)}"


def _slope_text(metric: str, t: dict[str, Any]) -> str:
    u = words.unit(metric)
    nd = 0 if metric == "strides_per_day" else 1
    s = f"{t['slope_per_week']:+.{nd}f}{u} per week"
    if t["ci95"][0] is not None:
        s += f" (95 % CI {t['ci95'][0]:+.{nd}f} to {t['ci95'][1]:+.{nd}f})"
    return s.replace("-", "\u2212")


def _leg_summary(patient: Patient, metric: str, tr: dict[str, Any]) -> dict[str, Any]:
    ch, t = tr["change"], tr["trend"]
    slope = _slope_text(metric, t) if t["slope_per_week"] is not None else "not enough sessions"
    if t["slope_per_week"] is not None and t["ci95"][0] is not None:
        lo, hi = t["ci95"]
        slope += " \u2013 " + ("rising" if lo > 0 else "falling" if hi < 0 else "no clear slope")
    nd = 0 if metric == "strides_per_day" else 1
    return {"leg": leg_name(patient, tr["leg"]), "slope": slope, "n": t["n"],
            "baseline": words.value(ch["baseline"], metric, nd), "latest": words.value(ch["latest"], metric, nd),
            "delta": words.value(ch["delta"], metric, nd) if ch["delta"] is None else
            (f"{ch['delta']:+.{nd}f}{words.unit(metric)}").replace("-", "\u2212"),
            "direction": words.DIRECTION.get(ch["direction"], ch["direction"] or ""),
            "reasons": "; ".join(ch["reasons"] or [])}


def symmetry_chart(patient: Patient, sym: dict[str, Any], first: date, last: date, bucket: str) -> str:
    """The symmetry index of peak swing flexion per bucket, with the near-symmetric band."""
    period = "day" if bucket == "day" else "week"
    x = plots.date_axis(f"Local {period} ({patient.timezone})", first, last)
    rows = sym["buckets"]
    xs = [float((date.fromisoformat(b["start"][:10]) - first).days) for b in rows]
    si = [b["symmetry_index_pct"] for b in rows]
    ref, other = sym["reference_leg"], sym["other_leg"]
    series = [Series(f"{words.METRIC_SHORT['peak_swing_flexion_deg']}: symmetry index", xs, si, AFFECTED, None, 2.0,
                     markers=len(xs) <= 60)]
    y = plots.numeric_axis("symmetry index (%)", [0.0, 10.0, -10.0, *si])
    hb = [HBand("within \u00b110 % (near symmetric)", -10.0, 10.0)]
    return plots.chart(title=f"Symmetry of peak flexion ({ref} vs {other} leg), per {period}",
                       desc=f"Symmetry index per {period}; 0 % is symmetric, negative means the {ref} leg reaches less",
                       x=x, y=y, series=series, hbands=hb,
                       subtitle=f"0 % = both legs equal; below 0 = the {ref} leg reaches less than the {other}.")


def patient_page(db: DbSession, patient: Patient, *, bucket: str | None, session_page: int) -> dict[str, Any]:
    """Template context of the patient page."""
    tz = zone(patient.timezone)
    legs = trend_service.legs_with_data(db, patient.id)
    ref, _ = leg_roles(patient, legs)
    comp = data.completeness(db, patient, days=CALENDAR_DAYS)
    listing = patient_service.session_page(db, patient.id, offset=(session_page - 1) * SESSIONS_PER_PAGE,
                                           limit=SESSIONS_PER_PAGE)
    sessions, n_sessions = listing.items, listing.total
    first_session = patient_service.first_done_session(db, patient.id)
    first_day = (as_utc(first_session.started_at).astimezone(tz).date() if first_session else None)
    today = data.local_today(patient)
    span = (today - first_day).days if first_day else 0
    bucket = bucket if bucket in ("day", "week") else ("day" if span <= 90 else "week")
    charts, summaries = [], []
    if first_day is not None and legs:
        for metric in TREND_METRICS:
            per_leg = {leg: data.trends(db, patient, metric, leg, bucket) for leg in ("left", "right") if leg in legs}
            charts.append({"metric": metric, "title": words.METRIC_SHORT[metric],
                           "svg": trend_chart(patient, metric, per_leg, ref, bucket, first_day, today),
                           "legs": [_leg_summary(patient, metric, per_leg[leg])
                                    for leg in (ref, "left" if ref == "right" else "right") if leg in per_leg]})
        if len(legs) == 2:
            # The page's period: per day needs no pooled value arrays, which keeps a year of history fast.
            # Peak flexion only: range of motion shows both legs in its own chart, and each symmetry answer
            # recomputes both legs' buckets.
            sym = data.symmetry(db, patient, "peak_swing_flexion_deg", bucket)
            last_si = next((b for b in reversed(sym["buckets"])
                            if b["symmetry_index_pct"] is not None), None)
            sym_first = first_day - timedelta(days=first_day.weekday()) if bucket == "week" else first_day
            summaries.append({"svg": symmetry_chart(patient, sym, sym_first, today, bucket),
                              "latest": last_si})
    days = [(date.fromisoformat(d["date"]), d["n_strides"], d["n_sessions"]) for d in comp["per_day"]]
    calendar = plots.calendar_svg(days, title=f"Days with data, last {CALENDAR_DAYS // 7} weeks "
                                              f"(local days, {tz.key})")
    rows = []
    peaks = trend_service.session_medians(db, [s.id for s in sessions], "peak_swing_flexion_deg")
    for s in sessions:
        rows.append({"id": s.id, "when": words.local_time(s.started_at, tz), "activity": s.activity,
                     "status": words.STATUS.get(s.status, s.status), "failed": s.status == "failed",
                     "legs": [{"leg": leg, "n": n, "peak": words.value(median, "peak_swing_flexion_deg")}
                              for leg, (n, median) in sorted(peaks.get(s.id, {}).items())]})
    comp30 = data.completeness(db, patient, days=30)
    return {"patient": patient, "tz": tz.key, "legs": legs, "ref": ref, "bucket": bucket, "charts": charts,
            "symmetry": summaries, "calendar": calendar, "sessions": rows, "n_sessions": n_sessions,
            "session_page": session_page, "n_session_pages": max(1, math.ceil(n_sessions / SESSIONS_PER_PAGE)),
            "days_with_data_30": comp30["days_with_data"], "strides_30": comp30["strides_total"],
            "walking_min_30": comp30["walking_min_total"],
            "calibrations": [{"leg": leg_name(patient, c.leg), "value": f"{c.standing_knee_deg:.1f}\u00b0",
                              "method": c.method.replace("_", " "), "when": words.local_time(c.measured_at, tz)}
                             for c in data.calibrations(db, patient)],
            "last_session": words.local_time(datetime_or_none(comp["last_session_at"]), tz)}


def datetime_or_none(s: str | None) -> datetime | None:
    """An ISO 8601 string as a datetime (None stays None)."""
    return datetime.fromisoformat(s) if s else None


# --- Session page --------------------------------------------------------------------------------------------

def cycle_chart(patient: Patient, leg: str, this: Cycle | None, first: Cycle | None,
                first_when: str, is_first: bool) -> str:
    """SVG of the knee angle over the gait cycle, this session against the first."""
    pct = [float(i) for i in range(CYCLE_POINTS)]
    series, bands, ys = [], [], []

    def add(c: Cycle, label: str, color: str, dash: str | None) -> None:
        lo = [None if m is None or s is None else m - s for m, s in zip(c.mean_deg, c.sd_deg, strict=True)]
        hi = [None if m is None or s is None else m + s for m, s in zip(c.mean_deg, c.sd_deg, strict=True)]
        ys.extend(c.mean_deg + lo + hi)
        bands.append(Band(f"{label}: \u00b1 1 SD", pct, lo, hi, color, 0.16))
        series.append(Series(f"{label}: mean of {c.n_strides} strides", pct, c.mean_deg, color, dash, 2.4))

    if first is not None and not is_first:
        add(first, f"First session ({first_when})", OTHER, "6 4")
    if this is not None:
        add(this, "This session", AFFECTED, None)
    x = Axis("gait cycle (% from heel strike to next heel strike)", 0, 100,
             [(float(v), f"{v}") for v in range(0, 101, 10)])
    y = plots.numeric_axis("knee flexion (\u00b0)", ys, include=[0])
    marks = [(this.toe_off_pct, f"toe-off {this.toe_off_pct:.0f} %", "#333333")] \
        if this is not None and this.toe_off_pct is not None else []
    return plots.chart(title=f"Knee angle over the gait cycle: {leg_name(patient, leg)}",
                       desc=f"Mean and standard deviation of knee flexion over the gait cycle, {leg} leg",
                       x=x, y=y, series=series, bands=bands, vlines=marks,
                       subtitle="Stance from heel strike to toe-off, then swing with the flexion peak.")


def trace_chart(traces: list[TraceWindow], patient: Patient, start: float, end: float) -> str:
    """SVG of the continuous knee angle of both legs in a time window."""
    series, ys = [], [0.0]
    for tr, color, dash in zip(traces, (AFFECTED, OTHER), (None, "5 3"), strict=False):
        vals = [None if not math.isfinite(a) else float(a) for a in tr.angle_deg]
        ys += vals
        series.append(Series(leg_name(patient, tr.leg), tr.t_s.tolist(), vals, color, dash, 1.4))
    x = plots.numeric_axis("time since session start (s)", [start, end], pad=0.0, lo=start, hi=end, n=8)
    y = plots.numeric_axis("knee flexion (\u00b0)", ys)
    return plots.chart(title="Knee angle, continuous",
                       desc=f"Knee flexion from {start:.0f} s to {end:.0f} s; gaps in the data break the line",
                       x=x, y=y, series=series, frame=plots.Frame(width=960, plot_height=250))


def zoom_links(t_first: float, t_last: float, start: float, end: float) -> list[dict[str, Any]]:
    """Links that move and scale the trace window (plain GET links: no script needed)."""
    span = end - start
    whole = t_last - t_first
    centre = (start + end) / 2

    def win(a: float, b: float) -> dict[str, float]:
        a, b = max(t_first, a), min(t_last, b)
        return {"start": round(a, 2), "end": round(b, 2)}

    links = [{"label": "Whole session", **win(t_first, t_last)}]
    if span > 2:
        links.append({"label": "Zoom in \u00d72", **win(centre - span / 4, centre + span / 4)})
    if span < whole:
        links.append({"label": "Zoom out \u00d72", **win(centre - span, centre + span)})
        if start > t_first:
            links.append({"label": "\u2190 Earlier", **win(start - span / 2, end - span / 2)})
        if end < t_last:
            links.append({"label": "Later \u2192", **win(start + span / 2, end + span / 2)})
    links.append({"label": "First 10 s", **win(t_first, t_first + 10)})
    return links


def session_page(db: DbSession, patient: Patient, session: Session, *, start: float | None, end: float | None,
                 all_strides: bool) -> dict[str, Any]:
    """Template context of the session page."""
    tz = zone(patient.timezone)
    summary = session.summary or {}
    ctx: dict[str, Any] = {
        "patient": patient, "session": session, "tz": tz.key, "when": words.local_time(session.started_at, tz),
        "status": words.STATUS.get(session.status, session.status), "error": session.error,
        "warnings": list(summary.get("warnings") or []), "done": session.status == "done",
        "processed": words.local_time(session.processed_at, tz) if session.processed_at else None,
        "algorithm": session.algorithm_version, "cycles": [], "trace": None, "strides": [], "n_strides": 0,
    }
    if session.status != "done":
        return ctx
    first = patient_service.first_done_session(db, patient.id)
    is_first = first is None or first.id == session.id
    rows = results_service.strides(db, session.id)
    excluded = stride_exclusions(rows)
    stored = results_service.traces(db, session.id)
    this_cycles = results_service.gait_cycles(db, session.id, rows, excluded, stored)
    first_cycles = results_service.gait_cycles(db, first.id) if first is not None and not is_first else {}
    first_when = words.local_date(first.started_at, tz) if first is not None else ""
    for leg in sorted(set(this_cycles) | set(first_cycles)):
        ctx["cycles"].append({"leg": leg, "svg": cycle_chart(patient, leg, this_cycles.get(leg),
                                                            first_cycles.get(leg), first_when, is_first),
                              "n": this_cycles[leg].n_strides if leg in this_cycles else 0})
    ctx["is_first"] = is_first
    traces = data.knee_angle(stored, start_s=start, end_s=end)
    if traces and max(t.n_total for t in traces) < 2:  # a window outside the recording: show all of it
        start = end = None
        traces = data.knee_angle(stored)
    if traces:
        t_first = min(t.t_first_s for t in traces)
        t_last = max(t.t_last_s for t in traces)
        a = t_first if start is None else max(t_first, start)
        b = t_last if end is None else min(t_last, end)
        if b <= a:
            a, b = t_first, t_last
            traces = data.knee_angle(stored)
        ctx["trace"] = {"svg": trace_chart(traces, patient, a, b), "links": zoom_links(t_first, t_last, a, b),
                        "start": round(a, 2), "end": round(b, 2), "t_first": round(t_first, 2),
                        "t_last": round(t_last, 2)}
    ctx["n_strides"] = len(rows)
    ctx["n_included"] = sum(1 for why in excluded if not why)
    shown = len(rows) if all_strides else STRIDES_SHOWN
    for s, excl in list(zip(rows, excluded, strict=True))[:shown]:
        ctx["strides"].append({
            "leg": s.leg, "index": s.index, "t": s.t_start_s,
            "clock": words.local_time(s.started_at, tz, with_date=False),
            "duration": s.duration_s, "peak": s.peak_swing_flexion_deg, "min": s.min_flexion_deg,
            "rom": s.rom_deg, "stance": s.stance_pct, "estimator": s.estimator, "quality": s.quality,
            "reasons": [words.reason(r) for r in (s.quality_reasons or [])],
            "excluded": [words.exclusion(e) for e in excl],
            "zoom": {"start": round(max(0.0, s.t_start_s - 1.0), 2), "end": round(s.t_end_s + 1.0, 2)}})
    ctx["all_strides"] = all_strides or len(rows) <= STRIDES_SHOWN
    return ctx


def compare_page(factory: sessionmaker[DbSession], principal: Principal, patient: Patient, session: Session
                 ) -> dict[str, Any]:
    """The estimator comparison page of one session."""
    out = data.compare(factory, principal, session)
    legs = []
    for leg, lc in sorted(out.legs.items()):
        legs.append({"leg": leg_name(patient, leg), "rows": [
            {"name": words.ESTIMATORS.get(name, name), "code": name, "n": es.n_strides,
             "peak": words.value(es.peak_swing_flexion_deg.mean, "peak_swing_flexion_deg"),
             "rom": words.value(es.rom_deg.mean, "rom_deg"),
             "min": words.value(es.min_flexion_deg.mean, "min_flexion_deg")} for name, es in lc.estimators.items()],
            "pairs": [{"a": words.ESTIMATORS.get(p.a, p.a), "b": words.ESTIMATORS.get(p.b, p.b),
                       "rms": words.value(p.rms_deg, "rom_deg"), "mean": words.value(p.mean_deg, "rom_deg"),
                       "n": p.n_samples} for p in lc.pairs]})
    return {"patient": patient, "session": session, "when": words.local_time(session.started_at,
                                                                             zone(patient.timezone)),
            "legs": legs, "failed": {words.ESTIMATORS.get(k, k): v for k, v in out.failed.items()},
            "warnings": out.warnings, "algorithm": out.algorithm_version}
