"""Snapshot regression of pipeline outputs: stride tables and trace hashes of fixed inputs.

The golden files in ``tests/pipeline/snapshots/`` were written by this test from the code as it was when they were
last updated. Any change of a stride value beyond 1e-6, of a stride count, of a warning, or of the continuous trace
(rounded to 1e-4 deg) fails the test. A deliberate accuracy change regenerates them in the same commit and says why::

    GAITMON_UPDATE_SNAPSHOTS=1 .venv/bin/pytest tests/pipeline/test_snapshots.py

Only the public entry points are used (``process_session``, ``detect_gait_events``, the simulator and the real-data
loaders), so the snapshots survive any restructuring behind them. Fields that a golden stride does not hold (added
later) are not compared; a golden field that disappears fails.
"""

from __future__ import annotations

import dataclasses
import hashlib
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


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def _trace_fingerprint(angle_deg: np.ndarray, estimator: np.ndarray, t_s: np.ndarray) -> dict:
    angle = np.asarray(angle_deg, dtype=float)
    finite = np.isfinite(angle)
    rounded = np.where(finite, np.round(angle, TRACE_DECIMALS), 0.0) + 0.0  # +0.0: no negative zeros
    return {
        "n": int(angle.size),
        "t_first_s": round(float(t_s[0]), VALUE_DECIMALS) if t_s.size else None,
        "t_last_s": round(float(t_s[-1]), VALUE_DECIMALS) if t_s.size else None,
        "n_finite": int(finite.sum()),
        "mean_deg": round(float(angle[finite].mean()), 3) if finite.any() else None,
        "angle_hash": _digest(rounded) + _digest(finite),
        "estimator_hash": hashlib.sha256("|".join(np.asarray(estimator).astype(str)).encode()).hexdigest()[:16],
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
            "trace": _trace_fingerprint(lr.angle_deg, lr.estimator, np.asarray(lr.t_s)),
            "strides": [{k: _round(v) for k, v in dataclasses.asdict(s).items()} for s in lr.strides],
        }
    return {"activity": result.activity, "warnings": list(result.warnings), "legs": legs}


def _compare(expected: object, actual: object, path: str) -> list[str]:
    """Differences between a golden value and a new one; new dict keys are allowed, missing ones are not."""
    if isinstance(expected, dict):
        if not isinstance(actual, dict):
            return [f"{path}: expected an object, got {actual!r}"]
        out = []
        for k, v in expected.items():
            if k not in actual:
                out.append(f"{path}.{k}: missing")
            else:
                out += _compare(v, actual[k], f"{path}.{k}")
        return out
    if isinstance(expected, list):
        if not isinstance(actual, list) or len(actual) != len(expected):
            n = len(actual) if isinstance(actual, list) else "?"
            return [f"{path}: expected {len(expected)} items, got {n}"]
        out = []
        for i, (e, a) in enumerate(zip(expected, actual, strict=True)):
            out += _compare(e, a, f"{path}[{i}]")
        return out
    if isinstance(expected, float) and isinstance(actual, (int, float)):
        return [] if abs(expected - actual) <= 1.5 * 10 ** -VALUE_DECIMALS else [f"{path}: {expected} -> {actual}"]
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
