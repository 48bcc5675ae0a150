"""Server-rendered SVG charts of the clinician pages: plain data in, one self-contained SVG string out.

No JavaScript and nothing fetched: the SVG is inlined in the HTML, scales with the page (``viewBox``), names every
axis with its unit, and carries ``<title>``/``<desc>`` plus ``role="img"`` so a screen reader announces what it
shows. Colours keep a contrast of at least 4.5:1 against white and every series also differs by dash pattern, so
the charts survive greyscale printing and colour-blindness.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import date, timedelta
from html import escape
from itertools import count

# Affected leg / this session: blue; other leg / first session: dark orange; both pass 4.5:1 on white.
AFFECTED = "#0b5cad"
OTHER = "#a04a00"
NEUTRAL = "#555555"
BAND = "#2e7d32"

_ids = count(1)


@dataclass(frozen=True)
class Axis:
    """An axis: its label (with the unit), its range and its ticks as (position, text)."""

    label: str
    lo: float
    hi: float
    ticks: Sequence[tuple[float, str]]


@dataclass(frozen=True)
class Series:
    """A line (None breaks it) with optional markers at each point."""

    name: str
    x: Sequence[float]
    y: Sequence[float | None]
    color: str = AFFECTED
    dash: str | None = None
    width: float = 2.0
    markers: bool = False


@dataclass(frozen=True)
class Band:
    """A shaded area between ``lo`` and ``hi`` along ``x`` (e.g. mean +- SD); None breaks it."""

    name: str
    x: Sequence[float]
    lo: Sequence[float | None]
    hi: Sequence[float | None]
    color: str = AFFECTED
    opacity: float = 0.18


@dataclass(frozen=True)
class HBand:
    """A horizontal band over the whole plot (e.g. baseline +- minimal detectable change)."""

    name: str
    y0: float
    y1: float
    color: str = BAND
    opacity: float = 0.16


@dataclass
class Frame:
    """Pixel geometry: title rows on top, the plot area, the x axis, then the legend rows (see :func:`chart`)."""

    width: int = 600
    plot_height: int = 220
    left: int = 64
    right: int = 14
    top: int = 30
    axis: int = 44  # below the plot: tick labels and the axis label
    legend_rows: int = 0
    extra: list[str] = field(default_factory=list)

    @property
    def plot_w(self) -> float:
        return self.width - self.left - self.right

    @property
    def plot_h(self) -> float:
        return self.plot_height

    @property
    def height(self) -> int:
        return self.top + self.plot_height + self.axis + 20 * self.legend_rows + 6


def nice_step(span: float, n: int) -> float:
    """A 1-2-5 step giving about ``n`` intervals over ``span``."""
    raw = span / max(n, 1)
    if raw <= 0 or not math.isfinite(raw):
        return 1.0
    mag = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 2.5, 5, 10):
        if raw <= m * mag:
            return m * mag
    return 10 * mag


def numeric_axis(label: str, values: Sequence[float | None], *, n: int = 5, pad: float = 0.05,
                 include: Sequence[float] = (), lo: float | None = None, hi: float | None = None) -> Axis:
    """An axis spanning the finite ``values`` (and ``include``), widened to round tick values."""
    finite = [float(v) for v in (*values, *include) if v is not None and math.isfinite(v)]
    vlo = lo if lo is not None else (min(finite) if finite else 0.0)
    vhi = hi if hi is not None else (max(finite) if finite else 1.0)
    if vhi - vlo < 1e-9:
        vlo, vhi = vlo - 1.0, vhi + 1.0
    span = vhi - vlo
    if lo is None:
        vlo -= pad * span
    if hi is None:
        vhi += pad * span
    step = nice_step(vhi - vlo, n)
    a = vlo if lo is not None else math.floor(vlo / step) * step
    b = vhi if hi is not None else math.ceil(vhi / step) * step
    ticks = []
    t = math.ceil(a / step - 1e-9) * step
    while t <= b + 1e-9:
        ticks.append((t, _fmt(t, step)))
        t += step
    return Axis(label, a, b, ticks)


def date_axis(label: str, first: date, last: date, *, n: int = 6) -> Axis:
    """A calendar axis; positions are days since ``first`` (dates are the patient's local days)."""
    span = max((last - first).days, 1)
    step = next((s for s in (1, 2, 7, 14, 28, 56, 91, 182, 364) if span / s <= n), 364)
    ticks = []
    d = first
    if step >= 7:  # week-aligned ticks start on a Monday
        d = first + timedelta(days=(7 - first.weekday()) % 7)
    while d <= last:
        fmt = f"{d.day} {d:%b}" if step < 182 else f"{d:%b %Y}"
        ticks.append((float((d - first).days), fmt))
        d += timedelta(days=step)
    return Axis(label, -0.5, span + 0.5, ticks)


def _fmt(v: float, step: float) -> str:
    if abs(v) < 1e-9:
        v = 0.0
    decimals = max(0, -math.floor(math.log10(step))) if step < 1 else 0
    if step < 1 and abs(step * 10 ** decimals - round(step * 10 ** decimals)) > 1e-6:
        decimals += 1
    return f"{v:.{decimals}f}".replace("-", "\u2212")


def _sx(fr: Frame, ax: Axis, v: float) -> float:
    return fr.left + (v - ax.lo) / (ax.hi - ax.lo) * fr.plot_w


def _sy(fr: Frame, ax: Axis, v: float) -> float:
    return fr.top + fr.plot_h - (v - ax.lo) / (ax.hi - ax.lo) * fr.plot_h


def _runs(x: Sequence[float], *ys: Sequence[float | None]) -> list[list[int]]:
    """Index runs where every ``ys`` value is finite."""
    runs: list[list[int]] = []
    cur: list[int] = []
    for i in range(len(x)):
        if all(y[i] is not None and math.isfinite(y[i]) for y in ys):  # type: ignore[arg-type]
            cur.append(i)
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    return runs


def _clip(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)


def chart(*, title: str, desc: str, x: Axis, y: Axis, series: Sequence[Series] = (), bands: Sequence[Band] = (),  # noqa: C901 - one optional layer per argument
          hbands: Sequence[HBand] = (), frame: Frame | None = None, subtitle: str = "",
          vlines: Sequence[tuple[float, str, str]] = ()) -> str:
    """One line chart as an SVG string: title, legend, grid, axis ticks and labels, bands, lines, and labelled
    vertical markers ``vlines`` = (x, label, colour)."""
    fr = frame or Frame()
    fr.top = 50 if subtitle else 32
    items = ([(s.name, s.color, s.dash, "line") for s in series] + [(b.name, b.color, None, "box") for b in bands]
             + [(h.name, h.color, None, "box") for h in hbands])
    rows = _legend_rows(fr, items)
    fr.legend_rows = len(rows)
    uid = f"c{next(_ids)}"
    out: list[str] = [
        f'<svg xmlns="http://www.w3.org/2000/svg" class="chart" viewBox="0 0 {fr.width} {fr.height}" role="img" '
        f'aria-labelledby="{uid}t {uid}d" preserveAspectRatio="xMidYMid meet">',
        f'<title id="{uid}t">{escape(title)}</title><desc id="{uid}d">{escape(desc)}</desc>',
        f'<text x="{fr.left}" y="18" class="ct">{escape(title)}</text>',
    ]
    if subtitle:
        out.append(f'<text x="{fr.left}" y="35" class="cs">{escape(subtitle)}</text>')
    x0, x1, y0, y1 = fr.left, fr.left + fr.plot_w, fr.top, fr.top + fr.plot_h
    out.append(f'<rect x="{x0}" y="{y0}" width="{fr.plot_w:.1f}" height="{fr.plot_h:.1f}" class="pa"/>')
    for v, label in y.ticks:
        py = _sy(fr, y, v)
        out.append(f'<line x1="{x0}" x2="{x1:.1f}" y1="{py:.1f}" y2="{py:.1f}" class="gr"/>'
                   f'<text x="{x0 - 6}" y="{py + 4:.1f}" class="tk" text-anchor="end">{escape(label)}</text>')
    for v, label in x.ticks:
        px = _sx(fr, x, v)
        out.append(f'<line x1="{px:.1f}" x2="{px:.1f}" y1="{y1:.1f}" y2="{y1 + 5:.1f}" class="ax"/>'
                   f'<text x="{px:.1f}" y="{y1 + 18:.1f}" class="tk" text-anchor="middle">{escape(label)}</text>')
    out.append(f'<text x="{(x0 + x1) / 2:.1f}" y="{y1 + fr.axis - 8}" class="al" text-anchor="middle">'
               f'{escape(x.label)}</text>')
    out.append(f'<text transform="translate(14 {(y0 + y1) / 2:.1f}) rotate(-90)" class="al" '
               f'text-anchor="middle">{escape(y.label)}</text>')
    out.append(f'<clipPath id="{uid}k"><rect x="{x0}" y="{y0}" width="{fr.plot_w:.1f}" '
               f'height="{fr.plot_h:.1f}"/></clipPath><g clip-path="url(#{uid}k)">')
    for hb in hbands:
        ya, yb = _sy(fr, y, _clip(max(hb.y0, hb.y1), y.lo, y.hi)), _sy(fr, y, _clip(min(hb.y0, hb.y1), y.lo, y.hi))
        out.append(f'<rect x="{x0}" y="{ya:.1f}" width="{fr.plot_w:.1f}" height="{max(yb - ya, 0):.1f}" '
                   f'fill="{hb.color}" fill-opacity="{hb.opacity}"><title>{escape(hb.name)}</title></rect>')
    for b in bands:
        for run in _runs(b.x, b.lo, b.hi):
            top = [f"{_sx(fr, x, b.x[i]):.1f},{_sy(fr, y, b.hi[i]):.1f}" for i in run]  # type: ignore[arg-type]
            bot = [f"{_sx(fr, x, b.x[i]):.1f},{_sy(fr, y, b.lo[i]):.1f}" for i in reversed(run)]  # type: ignore[arg-type]
            out.append(f'<polygon points="{" ".join(top + bot)}" fill="{b.color}" fill-opacity="{b.opacity}" '
                       f'class="band"/>')
    for s in series:
        dash = f' stroke-dasharray="{s.dash}"' if s.dash else ""
        parts = []
        for run in _runs(s.x, s.y):
            pts = [f"{_sx(fr, x, s.x[i]):.1f},{_sy(fr, y, s.y[i]):.1f}" for i in run]  # type: ignore[arg-type]
            parts.append("M" + "L".join(pts))
        if parts:
            out.append(f'<path d="{"".join(parts)}" fill="none" stroke="{s.color}" stroke-width="{s.width}" '
                       f'stroke-linejoin="round"{dash} class="series"><title>{escape(s.name)}</title></path>')
        if s.markers:
            for i in range(len(s.x)):
                v = s.y[i]
                if v is not None and math.isfinite(v):
                    out.append(f'<circle cx="{_sx(fr, x, s.x[i]):.1f}" cy="{_sy(fr, y, v):.1f}" r="2.6" '
                               f'fill="{s.color}"/>')
    for vx, label, color in vlines:
        if x.lo <= vx <= x.hi:
            px = _sx(fr, x, vx)
            out.append(f'<line x1="{px:.1f}" x2="{px:.1f}" y1="{y0}" y2="{y1:.1f}" stroke="{color}" '
                       f'stroke-width="1.5" stroke-dasharray="2 3"/><text x="{px + 4:.1f}" y="{y0 + 14}" '
                       f'class="lg" fill="{color}">{escape(label)}</text>')
    out.append("</g>")
    out.extend(fr.extra)
    out.append(_legend(fr, rows, y1 + fr.axis + 14))
    out.append(f'<rect x="{x0}" y="{y0}" width="{fr.plot_w:.1f}" height="{fr.plot_h:.1f}" class="fr"/></svg>')
    return "".join(out)


LegendItem = tuple[str, str, str | None, str]
_CHAR_W = 7.0  # average width of a 13 px legend character


def _legend_rows(fr: Frame, items: list[LegendItem]) -> list[list[tuple[float, LegendItem]]]:
    """Legend entries laid out left to right, wrapping onto as many rows as needed below the plot."""
    rows: list[list[tuple[float, LegendItem]]] = []
    px = float(fr.left)
    for it in items:
        w = 28 + _CHAR_W * len(it[0])
        if not rows or (px + w > fr.width - fr.right and px > fr.left):
            rows.append([])
            px = float(fr.left)
        rows[-1].append((px, it))
        px += w + 16
    return rows


def _legend(fr: Frame, rows: list[list[tuple[float, LegendItem]]], y0: float) -> str:
    out = []
    for r, row in enumerate(rows):
        py = y0 + 20 * r
        for px, (name, color, dash, kind) in row:
            if kind == "line":
                d = f' stroke-dasharray="{dash}"' if dash else ""
                out.append(f'<line x1="{px:.1f}" x2="{px + 22:.1f}" y1="{py - 4:.1f}" y2="{py - 4:.1f}" '
                           f'stroke="{color}" stroke-width="2.8"{d}/>')
            else:
                out.append(f'<rect x="{px:.1f}" y="{py - 10:.1f}" width="22" height="11" fill="{color}" '
                           f'fill-opacity="0.3"/>')
            out.append(f'<text x="{px + 27:.1f}" y="{py:.1f}" class="lg">{escape(name)}</text>')
    return "".join(out)


def calendar_svg(days: Sequence[tuple[date, int, int]], *, title: str) -> str:
    """Weeks as columns, weekdays as rows: each local day a square, darker with more trustworthy strides.

    ``days`` are (local date, strides, sessions) in date order. Days with sessions but no trustworthy stride are
    hatched so "wore the sensors, nothing usable" differs from "no session".
    """
    if not days:
        return ""
    first = days[0][0]
    start = first - timedelta(days=first.weekday())
    cell, gap, left, top = 14, 3, 34, 40
    n_weeks = (days[-1][0] - start).days // 7 + 1
    width = max(left + n_weeks * (cell + gap) + 10, left + 560)
    height = top + 7 * (cell + gap) + 30
    peak = max((n for _, n, _ in days), default=0) or 1
    uid = f"c{next(_ids)}"
    n_data = sum(1 for _, n, _ in days if n > 0)
    desc = f"{n_data} of {len(days)} days from {first:%d %b %Y} to {days[-1][0]:%d %b %Y} have trustworthy strides"
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" class="chart calendar" viewBox="0 0 {width} {height}" '
           f'role="img" aria-labelledby="{uid}t {uid}d">',
           f'<title id="{uid}t">{escape(title)}</title><desc id="{uid}d">{escape(desc)}</desc>',
           f'<defs><pattern id="{uid}h" width="4" height="4" patternUnits="userSpaceOnUse">'
           f'<path d="M0,4 L4,0" stroke="{OTHER}" stroke-width="1.2"/></pattern></defs>',
           f'<text x="0" y="16" class="ct">{escape(title)}</text>']
    for r, name in enumerate(("Mon", "", "Wed", "", "Fri", "", "Sun")):
        if name:
            out.append(f'<text x="0" y="{top + r * (cell + gap) + 11}" class="tk">{name}</text>')
    month = None
    for d, n, k in days:
        col = (d - start).days // 7
        row = d.weekday()
        x, y = left + col * (cell + gap), top + row * (cell + gap)
        if d.month != month and row <= 3:
            month = d.month
            out.append(f'<text x="{x}" y="{top - 6}" class="tk">{d:%b}</text>')
        if n > 0:
            level = 0.25 + 0.75 * min(n / peak, 1.0)
            fill = f'fill="{AFFECTED}" fill-opacity="{level:.2f}"'
        elif k > 0:
            fill = f'fill="url(#{uid}h)"'
        else:
            fill = 'fill="#eeeeee"'
        what = (f"{n} trustworthy strides in {k} session{'s' if k != 1 else ''}" if n > 0 else
                f"{k} session{'s' if k != 1 else ''}, no trustworthy stride" if k > 0 else "no session")
        out.append(f'<rect x="{x}" y="{y}" width="{cell}" height="{cell}" rx="2" {fill} stroke="#999" '
                   f'stroke-width="0.5" class="day"><title>{d:%a %d %b %Y}: {what}</title></rect>')
    ly = height - 10
    out.append(f'<rect x="{left}" y="{ly - 10}" width="12" height="12" fill="#eeeeee" stroke="#999" '
               f'stroke-width="0.5"/><text x="{left + 16}" y="{ly}" class="lg">no session</text>'
               f'<rect x="{left + 96}" y="{ly - 10}" width="12" height="12" fill="url(#{uid}h)" stroke="#999" '
               f'stroke-width="0.5"/><text x="{left + 112}" y="{ly}" class="lg">session, no usable strides</text>'
               f'<rect x="{left + 290}" y="{ly - 10}" width="12" height="12" fill="{AFFECTED}" fill-opacity="0.6"/>'
               f'<text x="{left + 306}" y="{ly}" class="lg">strides (darker = more, up to {peak})</text></svg>')
    return "".join(out)
