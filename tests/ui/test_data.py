"""The page data layer against the service layer it stands in for (no browser)."""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np

from server.trends.metrics import METRICS, MIN_QUALITY, stride_exclusions
from server.ui import plots


def _rule(row: SimpleNamespace) -> list[str]:
    """The exclusion rule stated stride by stride, as a clinician would read it."""
    if row.quality is None or row.quality < MIN_QUALITY:
        return [f"quality<{MIN_QUALITY:g}"]
    return [f"implausible:{name}" for name, m in METRICS.items()
            if m.column is not None and not m.plausible(m.values(np.array([getattr(row, m.column)], float)))[0]]


def test_exclusions_column_wise_match_the_rule_stride_by_stride() -> None:
    rng = np.random.default_rng(3)
    columns = sorted({m.column for m in METRICS.values() if m.column})
    rows = []
    for i in range(400):
        values = {c: float(rng.uniform(-40, 170)) for c in columns}
        values["duration_s"] = float(rng.choice([0.0, 0.3, 1.1, 5.0]))
        values["swing_time_s"] = float(rng.uniform(0.0, 2.5))
        values["stance_pct"] = float(rng.uniform(20, 95))
        if i % 17 == 0:
            values["rom_deg"] = float("nan")
        quality = None if i % 50 == 0 else float(rng.choice([0.2, 0.49, 0.5, 0.9, 1.0]))
        rows.append(SimpleNamespace(quality=quality, **values))
    got = stride_exclusions(rows)
    assert got == [_rule(r) for r in rows]
    assert any(got) and not all(got)  # both outcomes occur


def test_nice_axis_covers_the_data_with_round_ticks() -> None:
    ax = plots.numeric_axis("knee flexion (deg)", [3.2, 61.7, None])
    assert ax.lo <= 3.2 and ax.hi >= 61.7
    steps = {round(b[0] - a[0], 9) for a, b in zip(ax.ticks, ax.ticks[1:], strict=False)}
    assert len(steps) == 1 and steps.pop() in (5.0, 10.0, 20.0)


def test_chart_breaks_lines_at_gaps_and_names_itself() -> None:
    svg = plots.chart(title="T", desc="D", x=plots.numeric_axis("x (s)", [0, 4]),
                      y=plots.numeric_axis("y (deg)", [0, 1]),
                      series=[plots.Series("s", [0, 1, 2, 3, 4], [0.0, 1.0, None, 1.0, 0.5])])
    paths = re.findall(r'<path d="([^"]+)"', svg)
    assert len(paths) == 1 and paths[0].count("M") == 2  # one line, two runs around the gap
    assert 'role="img"' in svg and "<title" in svg and "x (s)" in svg and "y (deg)" in svg
