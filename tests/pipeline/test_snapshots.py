"""Snapshot regression of pipeline outputs: stride tables and per-second trace means of fixed inputs.

The golden files in ``tests/pipeline/snapshots/`` were written by this test from the code as it was when they were
last updated. Any change of a stride count, a warning, an estimator or a quality reason fails the test, and so does a
value that moves by more than its unit's tolerance (``TOLERANCE``): the trace is compared as one mean per second.
The tolerances are not zero because the same code gives slightly different floats on different CPUs (numpy's and
OpenBLAS's SIMD kernels are chosen at run time), and a last-bit difference can move a stride edge by one sample; the
largest differences seen between two machines (0.14 deg, one sample, 0.45 %) are below them, and an algorithm change
that a clinician would notice is not. A deliberate accuracy change regenerates them in the same commit and says why::

    GAITMON_UPDATE_SNAPSHOTS=1 .venv/bin/pytest tests/pipeline/test_snapshots.py

Only the public entry points are used (``process_session``, ``detect_gait_events``, the simulator and the real-data
loaders), so the snapshots survive any restructuring behind them. Fields that a golden stride does not hold (added
later) are not compared; a golden field that disappears fails.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

from bench.real_data import BIOMECHZOO_CSV, TAN_DIR, load_biomechzoo, load_tan_steps, real_data_available
from pipeline.phases import detect_gait_events, shank_sagittal_dps
from pipeline.session import process_session
from pipeline.simulate import SimConfig, simulate_session
from tests.conftest import skip_without_real_data

SNAPSHOT_DIR = Path(__file__).parent / "snapshots"
UPDATE = os.environ.get("GAITMON_UPDATE_SNAPSHOTS") == "1"
VALUE_DECIMALS = 6
TRACE_DECIMALS = 4
TRACE_BLOCK_S = 1.0
# allowed |golden - new| by the unit suffix of a field's name; other floats must agree to VALUE_DECIMALS
TOLERANCE = {"_deg": 0.25, "_s": 0.021, "_pct": 1.0}  # 0.021 s: one sample at the lowest rate simulated (50 Hz)
COUNT_TOLERANCE = 0.005  # samples (finite, per estimator) may move by this share of the trace

# (case name, simulator config, activity uploaded, estimators): short sessions that still cover every path
SIM_CASES: list[tuple[str, SimConfig, str, tuple[str, ...]]] = [
    ("sim_normal_100hz", SimConfig(pattern="normal", fs_hz=100.0, seed=901, duration_s=75.0), "walking",
     ("auto", "go", "cf", "kf", "ekf")),
    ("sim_crouch_50hz", SimConfig(pattern="crouch", fs_hz=50.0, seed=902, duration_s=60.0), "walking", ("auto",)),
    ("sim_stiff_200hz", SimConfig(pattern="stiff-knee", fs_hz=200.0, seed=903, duration_s=45.0), "walking",
     ("auto",)),
    ("sim_running_200hz", SimConfig(pattern="running", fs_hz=200.0, seed=904, duration_s=45.0), "running",
     ("auto", "ekf")),
    ("sim_running_unknown", SimConfig(pattern="running", fs_hz=100.0, seed=905, duration_s=45.0), "unknown",
     ("auto",)),
    ("sim_fast_unknown", SimConfig(pattern="fast", fs_hz=100.0, seed=906, duration_s=60.0), "unknown", ("auto",)),
    ("sim_lossy_normal", SimConfig(pattern="normal", fs_hz=128.0, seed=907, duration_s=60.0, packet_loss=0.03,
                                   packet_samples=20), "walking", ("auto",)),
]


def _trace_fingerprint(angle_deg: np.ndarray, estimator: np.ndarray, t_s: np.ndarray, fs_hz: float) -> dict:
    angle = np.asarray(angle_deg, dtype=float)
    finite = np.isfinite(angle)
    block = max(1, round(TRACE_BLOCK_S * fs_hz))
    block_means = []
    for i in range(0, angle.size, block):
        seg = angle[i:i + block][finite[i:i + block]]
        block_means.append(round(float(seg.mean()), TRACE_DECIMALS) + 0.0 if seg.size else None)
    labels, counts = np.unique(np.asarray(estimator).astype(str), return_counts=True)
    return {
        "n": int(angle.size),
        "t_first_s": round(float(t_s[0]), VALUE_DECIMALS) if t_s.size else None,
        "t_last_s": round(float(t_s[-1]), VALUE_DECIMALS) if t_s.size else None,
        "n_finite": int(finite.sum()),
        "mean_deg": round(float(angle[finite].mean()), 3) if finite.any() else None,
        "block_mean_deg": block_means,
        "estimator_samples": {str(k): int(c) for k, c in zip(labels, counts, strict=True)},
    }


def _round(v: object) -> object:
    if isinstance(v, float):
        return round(v, VALUE_DECIMALS) + 0.0 if np.isfinite(v) else repr(v)
    if isinstance(v, (list, tuple)):
        return [_round(x) for x in v]
    return v


def _result_snapshot(result) -> dict:
    legs = {}
    for leg, lr in sorted(result.legs.items()):
        legs[leg] = {
            "fs_hz": round(float(lr.fs_hz), VALUE_DECIMALS),
            "trace": _trace_fingerprint(lr.angle_deg, lr.estimator, np.asarray(lr.t_s), float(lr.fs_hz)),
            "strides": [{k: _round(v) for k, v in dataclasses.asdict(s).items()} for s in lr.strides],
        }
    return {"activity": result.activity, "warnings": list(result.warnings), "legs": legs}


def _tolerance(key: str) -> float:
    return next((tol for suffix, tol in TOLERANCE.items() if key.endswith(suffix)), 1.5 * 10 ** -VALUE_DECIMALS)


def _compare(expected: object, actual: object, path: str, key: str = "", n_samples: int = 0) -> list[str]:
    """Differences between a golden value and a new one; new dict keys are allowed, missing ones are not.

    ``key`` is the name of the field the value sits under (its unit suffix picks the tolerance); ``n_samples`` the
    length of the trace whose sample counts are being compared.
    """
    if isinstance(expected, dict):
        if not isinstance(actual, dict):
            return [f"{path}: expected an object, got {actual!r}"]
        n_samples = expected.get("n", n_samples) if isinstance(expected.get("n"), int) else n_samples
        out = []
        for k, v in expected.items():
            if k not in actual:
                out.append(f"{path}.{k}: missing")
            else:
                sub_key = key if key == "estimator_samples" else k
                out += _compare(v, actual[k], f"{path}.{k}", sub_key, n_samples)
        if key == "estimator_samples":  # a label the golden trace never used is a change too
            out += [f"{path}.{k}: new, {v} samples" for k, v in actual.items()
                    if k not in expected and v > COUNT_TOLERANCE * n_samples]
        return out
    if isinstance(expected, list):
        if not isinstance(actual, list) or len(actual) != len(expected):
            n = len(actual) if isinstance(actual, list) else "?"
            return [f"{path}: expected {len(expected)} items, got {n}"]
        out = []
        for i, (e, a) in enumerate(zip(expected, actual, strict=True)):
            out += _compare(e, a, f"{path}[{i}]", key, n_samples)
        return out
    if isinstance(expected, int) and isinstance(actual, int) and key in ("n_finite", "estimator_samples"):
        ok = abs(expected - actual) <= COUNT_TOLERANCE * n_samples
        return [] if ok else [f"{path}: {expected} -> {actual}"]
    if isinstance(expected, float) and isinstance(actual, (int, float)):
        return [] if abs(expected - actual) <= _tolerance(key) else [f"{path}: {expected} -> {actual}"]
    return [] if expected == actual else [f"{path}: {expected!r} -> {actual!r}"]


def _check(name: str, actual: dict) -> None:
    path = SNAPSHOT_DIR / f"{name}.json"
    actual = json.loads(json.dumps(actual))  # tuples -> lists, as stored
    if UPDATE or not path.exists():
        if not UPDATE:
            pytest.fail(f"no snapshot {path.name}: run with GAITMON_UPDATE_SNAPSHOTS=1 to create it")
        SNAPSHOT_DIR.mkdir(exist_ok=True)
        path.write_text(json.dumps(actual, indent=1, sort_keys=True) + "\n")
        return
    diffs = _compare(json.loads(path.read_text()), actual, name)
    assert not diffs, f"{len(diffs)} differences from {path.name}:\n" + "\n".join(diffs[:30])


def test_compare_tolerates_cpu_noise_but_not_changes() -> None:
    golden = {"n": 1000, "n_finite": 990, "estimator_samples": {"go": 990}, "peak_swing_flexion_deg": 60.0,
              "t_start_s": 1.0, "quality": 0.75, "estimator": "go"}
    noise = {**golden, "n_finite": 994, "estimator_samples": {"go": 986, "cf": 4}, "peak_swing_flexion_deg": 60.14,
             "t_start_s": 1.0078}
    assert _compare(golden, noise, "case") == []
    for change in ({"peak_swing_flexion_deg": 60.3}, {"t_start_s": 1.03}, {"quality": 0.5}, {"estimator": "cf"},
                   {"n_finite": 980}, {"estimator_samples": {"go": 980, "cf": 10}}):
        assert _compare(golden, {**golden, **change}, "case"), change


@pytest.fixture(scope="module")
def simulated() -> dict[str, object]:
    return {name: simulate_session(cfg) for name, cfg, _, _ in SIM_CASES}


@pytest.mark.parametrize(("name", "activity", "estimators"), [(n, a, e) for n, _, a, e in SIM_CASES],
                         ids=[c[0] for c in SIM_CASES])
def test_simulated_session_snapshot(simulated, name: str, activity: str, estimators: tuple[str, ...]) -> None:
    sim = simulated[name]
    _check(name, {est: _result_snapshot(process_session(sim.streams, activity, estimator=est))
                  for est in estimators})


@pytest.mark.realdata
def test_biomechzoo_snapshot() -> None:
    skip_without_real_data(real_data_available(BIOMECHZOO_CSV), "biomechZoo trial")
    streams, _ = load_biomechzoo()
    _check("real_biomechzoo", {est: _result_snapshot(process_session(streams, "walking", estimator=est))
                               for est in ("auto", "go", "cf", "kf", "ekf")})


@pytest.mark.realdata
def test_tan_events_snapshot() -> None:
    skip_without_real_data(real_data_available(TAN_DIR), "Tan et al. steps")
    out = {}
    for w in load_tan_steps():
        ev = detect_gait_events(shank_sagittal_dps(w.shank_gyr_dps), w.fs_hz, min_bout_peaks=1,
                                shank_acc_mps2=w.shank_acc_mps2)
        out[f"{w.subject}_{w.step}"] = {"hs": ev.hs.tolist(), "to": ev.to.tolist()}
    _check("real_tan_events", out)
