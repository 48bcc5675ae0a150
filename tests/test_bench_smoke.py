"""Quick runs of the benchmark code (bench/): tables with the expected rows and columns and finite figures."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.accuracy import SIM_HEADER, Case, format_row, run_case, sim_table
from bench.matching import LegScore, bland_altman, match_strides, summarise
from pipeline.simulate import TruthStride
from pipeline.types import StrideMetrics

REPO = Path(__file__).resolve().parent.parent


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _stride(t0: float, t1: float, peak: float = 60.0) -> StrideMetrics:
    return StrideMetrics(leg="left", index=0, t_start_s=t0, t_end_s=t1, duration_s=t1 - t0,
                         t_toe_off_s=t0 + 0.6 * (t1 - t0), stance_time_s=0.6 * (t1 - t0),
                         swing_time_s=0.4 * (t1 - t0), stance_pct=60.0, peak_swing_flexion_deg=peak,
                         min_flexion_deg=3.0, rom_deg=peak - 3.0, stance_flexion_deg=15.0, estimator="go",
                         quality=1.0)


def _truth(t0: float, t1: float) -> TruthStride:
    return TruthStride(leg="left", t_start_s=t0, t_end_s=t1, t_toe_off_s=t0 + 0.6 * (t1 - t0),
                       peak_swing_flexion_deg=60.0, min_flexion_deg=3.0, rom_deg=57.0, stance_flexion_deg=15.0,
                       steady=True, turning=False)


def test_matching_is_one_to_one_within_tolerance() -> None:
    truth = [_truth(1.0 + k * 1.1, 2.1 + k * 1.1) for k in range(5)]
    detected = [
        _stride(1.02, 2.13),  # matches truth 0
        _stride(1.05, 2.16),  # a duplicate of the same stride: only one of the two may match
        _stride(3.5, 4.6),  # between strides 2 and 3: half a stride off, no match
        _stride(5.42, 6.48),  # truth 4 (5.4 .. 6.5)
    ]
    pairs = match_strides(detected, truth)
    assert sorted(j for _, j in pairs) == [0, 4]
    assert len({i for i, _ in pairs}) == len(pairs)
    assert (0, 0) in pairs  # the closer duplicate wins


def test_bland_altman_limits() -> None:
    bias, lo, hi = bland_altman([1.0, 3.0])
    assert bias == pytest.approx(2.0)
    assert hi - bias == pytest.approx(1.96 * math.sqrt(2.0))
    assert bias - lo == pytest.approx(hi - bias)
    assert all(math.isnan(x) for x in bland_altman([1.0]))


@pytest.fixture(scope="module")
def quick_scores() -> dict[str, LegScore]:
    _, scores, _ = run_case(Case("normal", 100.0, 100, 40.0), ["auto", "go"])
    return scores


def test_run_case_scores_every_estimator(quick_scores: dict[str, LegScore]) -> None:
    assert set(quick_scores) == {"auto", "go"}
    for sc in quick_scores.values():
        s = summarise(sc)
        assert s["n_true"] >= 20  # two legs, two short bouts
        for key in ("recall", "precision", "coverage", "peak_bias", "peak_lo", "peak_hi", "rom_bias", "rmse",
                    "hs_ms", "to_ms"):
            assert np.isfinite(s[key]), key
        assert 0.0 <= s["recall"] <= 1.0 and 0.0 <= s["precision"] <= 1.0
        assert s["peak_lo"] <= s["peak_bias"] <= s["peak_hi"]
        assert s["rmse"] > 0.0


def test_sim_table_rows_and_columns(quick_scores: dict[str, LegScore]) -> None:
    pooled = {(est, "normal"): sc for est, sc in quick_scores.items()}
    pooled[("auto", "running")] = LegScore()  # an empty pattern prints dashes, not a crash
    lines = sim_table(pooled, ["auto", "go"], ["normal", "crouch", "running"])
    header = _cells(lines[0])
    assert header[:2] == ["estimator", "pattern"] and header[2:] == SIM_HEADER
    rows = [_cells(x) for x in lines[2:]]
    assert all(len(r) == len(header) for r in rows)
    labels = [(r[0], r[1]) for r in rows]
    for est in ("`auto`", "`go`"):
        assert (est, "normal") in labels and (est, "**overall**") in labels and (est, "running †") in labels
    normal = rows[labels.index(("`auto`", "normal"))]
    assert float(normal[3].split()[0]) <= 1.0  # recall, possibly with a miss mark
    assert math.isfinite(float(normal[9].split()[0]))  # RMSE


def test_format_row_marks_misses() -> None:
    s = {"n_true": 10.0, "recall": 0.9, "precision": 1.0, "coverage": 0.9, "peak_bias": 2.0, "peak_lo": -1.0,
         "peak_hi": 5.0, "rom_bias": 0.0, "rom_lo": -1.0, "rom_hi": 1.0, "rmse": 1.0, "hs_ms": 10.0, "to_ms": 20.0}
    cells = _cells(format_row(["`go`", "normal"], s, targets=True))
    assert cells[3].endswith("✗") and not cells[4].endswith("✗")  # recall misses, precision meets
    assert cells[6].endswith("✗") and cells[7].endswith("✗")  # peak bias and LoA miss
    assert not cells[9].endswith("✗") and not cells[10].endswith("✗")  # ROM LoA and RMSE meet
    assert not any(c.endswith("✗") for c in _cells(format_row(["`go`", "running †"], s, targets=False)))


def test_accuracy_quick_cli_prints_tables() -> None:
    out = subprocess.run([sys.executable, "-m", "bench.accuracy", "--quick", "--no-real", "--estimators", "auto",
                          "--jobs", "1", "--minutes", "0.5"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    rows = [_cells(x) for x in out.stdout.splitlines() if x.startswith("| `auto`")]
    assert [r[1] for r in rows] == ["normal", "running †"]
    assert "[2/2]" in out.stderr


def test_speed_bench_runs() -> None:
    out = subprocess.run([sys.executable, "-m", "bench.speed", "--runs", "1", "--minutes", "0.5",
                          "--profile-top", "3"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    row = _cells(lines[lines.index("|---|---|---|---|---|") + 1])
    assert row[0] == "1" and float(row[1].split()[0]) > 0 and float(row[2]) > 0
    assert sum(1 for x in lines if x.startswith("| `pipeline.")) == 3


def test_pages_bench_times_every_page() -> None:
    out = subprocess.run([sys.executable, "-m", "bench.pages", "--days", "3", "--strides", "20", "--cohort", "2",
                          "--minutes", "0.5", "--repeats", "2"], cwd=REPO, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    rows = [x for x in out.stdout.splitlines() if x.strip().startswith(("My patients", "Patient", "Session"))]
    assert len(rows) == 10 and all(" ms " in r for r in rows)  # 5 pages, cold and warm
    assert "Estimator comparison" in out.stdout


def test_ingest_bench_uploads_through_a_real_server(capsys: pytest.CaptureFixture[str]) -> None:
    """bench.ingest end to end on SQLite: one phone, a short session, every batch stored, the session processed."""
    from bench.ingest import main

    assert main(["--phones", "1", "--minutes", "0.3", "--timeout-s", "120"]) == 0
    out = capsys.readouterr().out
    rows = {c[0]: c[1] for c in (_cells(line) for line in out.splitlines() if line.startswith("| ")) if len(c) == 2}
    stored = int(rows["batches stored"].split()[0])
    assert stored > 50
    assert float(rows["throughput"].split()[0]) > 0
    done = rows["complete -> all 1 sessions done"]  # e.g. "0.9 s (12 strides)"
    assert int(done.split("(")[1].split()[0]) > 0


def _table(stdout: str, axis: str) -> list[list[str]]:
    """The data rows of one axis table of bench.robustness."""
    lines = stdout.splitlines()
    start = next(i for i, x in enumerate(lines) if x.startswith("### ") and f"(`{axis}`)" in x)
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("### ") or line.startswith("## "):
            break
        if line.startswith("| ") and not line.startswith("| value"):
            rows.append(_cells(line))
    return rows


def test_robustness_quick_cli_prints_axis_tables() -> None:
    out = subprocess.run([sys.executable, "-m", "bench.robustness", "--quick", "--axes", "loss,labels", "--no-real",
                          "--jobs", "1"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "[4/4]" in out.stderr
    loss = _table(out.stdout, "loss")
    assert [r[0] for r in loss] == ["0 %", "1 %"]
    for r in loss:
        assert int(r[1]) > 10  # true strides
        recall, precision, coverage = (float(c.split()[0]) for c in r[2:5])
        assert 0.5 <= recall <= 1.0 and 0.5 <= precision <= 1.0 and 0.0 < coverage <= 1.0
        lo, hi = (float(x) for x in r[6].rstrip(" ✗").split(" .. "))
        assert lo <= float(r[5].split()[0]) <= hi  # peak LoA brackets the bias
        assert 0.0 < float(r[9].split()[0]) < 20.0  # RMSE inside strides
        assert float(r[10]) >= 0.0  # RMSE outside gait
        assert r[12].rstrip(" ✗").endswith("%")
    labels = _table(out.stdout, "labels")
    assert [r[0] for r in labels] == ["legs swapped (all four)", "legs swapped (all four), pelvis and hip 3-D x1"]
    assert all("legs out" in r[-1] for r in labels)
    # caught or not, the cell says which (detection: tests/pipeline/test_assignment.py)
    assert labels[1][-1].startswith(("detected in", "accepted"))
    assert float(labels[0][2].split()[0]) < 0.5  # scored against the labelled leg, the other leg's strides miss


def test_robustness_cases_change_one_assumption() -> None:
    from bench.robustness import AXES, Case, case_config, format_row

    base = case_config(Case("rate", 2, 7, 90.0))  # "100 Hz": the base case itself
    for name, axis in AXES.items():
        for i, value in enumerate(axis.values):
            cfg = case_config(Case(name, i, 7, 90.0))
            changed = {f.name for f in dataclasses.fields(cfg) if getattr(cfg, f.name) != getattr(base, f.name)}
            assert changed <= set(value.overrides), (name, value.label, changed)
    s = {"n_true": 10.0, "recall": 0.94, "precision": 0.99, "coverage": 0.9, "peak_bias": 1.6, "peak_lo": -1.0,
         "peak_hi": 3.0, "rom_bias": 0.0, "rom_lo": -1.0, "rom_hi": 1.0, "rmse_strides": 3.1, "rmse_outside": 9.0,
         "non_gait_strides": 0.0, "implausible_share": 0.0}
    cells = _cells(format_row("x", s, AXES["rate"].values[0].targets))
    assert cells[2].endswith("✗") and not cells[3].endswith("✗")  # recall misses 0.95, precision meets 0.98
    assert cells[4].endswith("✗")  # coverage 0.9 < 0.95
    assert cells[5].endswith("✗") and not cells[6].endswith("✗")  # bias misses 1.5, LoA inside +-3.5
    assert cells[9].endswith("✗") and not cells[10].endswith("✗")  # RMSE in strides misses; outside: no target
    assert not cells[11].endswith("✗") and not cells[12].endswith("✗")
    ten = next(v for v in AXES["loss"].values if v.label == "10 %")
    assert not _cells(format_row("x", s, ten.targets))[2].endswith("✗")  # 0.9 at 10 % bursty loss


def test_speed_bench_lengths_table() -> None:
    """The per-length table: one short block and one chunked session, gaitmon and the reference in subprocesses."""
    out = subprocess.run([sys.executable, "-m", "bench.speed", "--lengths", "1m,3m", "--chunk-s", "60"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    rows = [_cells(x) for x in lines if x.startswith("| 1m |") or x.startswith("| 3m |")]
    assert [r[0] for r in rows] == ["1m", "3m"]
    for r in rows:
        cpu_g, per_min, rss_g, cpu_r, _, rss_r, ratio = (float(x) for x in r[1:8])
        assert cpu_g > 0 and cpu_r > 0 and 50 < rss_g < 2000 and 50 < rss_r < 2000
        assert ratio == pytest.approx(cpu_g / cpu_r, rel=0.05, abs=0.01)
        n_g, n_r = (int(x) for x in r[8].split(" / "))
        assert n_g > 20 and n_r > 20
    assert rows[1][1] != rows[0][1]
    assert any(x.startswith("gaitmon CPU per minute at 3m / at 1m:") for x in lines)
