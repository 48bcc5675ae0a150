"""GET /v1/sessions/{id}/compare: every estimator side by side on a simulated running session."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from pipeline.simulate import SimConfig, simulate_session
from pipeline.types import LegResult, SessionResult, StrideMetrics
from server.config import Settings
from server.processing.jobs import run_queued
from server.results import compare
from server.results.compare import compare_results
from server.simulate_cli import session_to_requests
from tests.server.helpers import Api, bearer, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def _stride(peak: float, low: float, estimator: str) -> StrideMetrics:
    return StrideMetrics(leg="left", index=0, t_start_s=0.0, t_end_s=1.0, duration_s=1.0, t_toe_off_s=0.6,
                         stance_time_s=0.6, swing_time_s=0.4, stance_pct=60.0, peak_swing_flexion_deg=peak,
                         min_flexion_deg=low, rom_deg=peak - low, stance_flexion_deg=15.0, estimator=estimator,
                         quality=1.0)


def _result(angle: np.ndarray, peaks: list[float], estimator: str) -> SessionResult:
    t = np.arange(angle.size) / 100.0
    leg = LegResult(leg="left", fs_hz=100.0, t_s=t, angle_deg=angle, estimator=np.full(angle.size, estimator),
                    strides=[_stride(p, 2.0, estimator) for p in peaks])
    return SessionResult(algorithm_version="x", activity="walking", legs={"left": leg})


def test_pairwise_rms_and_summaries() -> None:
    base = np.sin(np.linspace(0, 20, 1000)) * 30 + 30
    shifted = base + 3.0
    noisy = base.copy()
    noisy[:100] = np.nan  # no estimate there: those samples do not count
    noisy[500:] += 4.0
    out = compare_results({"go": _result(base, [60, 62, 64], "go"), "cf": _result(shifted, [63], "cf"),
                           "kf": _result(noisy, [], "kf")})
    leg = out["left"]
    pairs = {(p.a, p.b): p for p in leg.pairs}
    assert set(pairs) == {("go", "cf"), ("go", "kf"), ("cf", "kf")}
    assert pairs[("go", "cf")].rms_deg == pytest.approx(3.0) and pairs[("go", "cf")].mean_deg == pytest.approx(-3.0)
    assert pairs[("go", "kf")].n_samples == 900
    assert pairs[("go", "kf")].rms_deg == pytest.approx(np.sqrt(500 * 16 / 900), abs=0.01)
    go = leg.estimators["go"]
    assert go.n_strides == 3 and go.peak_swing_flexion_deg.mean == 62.0 and go.peak_swing_flexion_deg.sd == 2.0
    assert go.rom_deg.median == 60.0 and go.stride_estimators == {"go": 3}
    assert leg.estimators["cf"].peak_swing_flexion_deg.sd is None  # one stride: no spread
    assert leg.estimators["kf"].n_strides == 0 and leg.estimators["kf"].rom_deg.mean is None


def test_compare_running_session_over_http(api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    other_clin = api.clinician("Dr. Other")[1]
    sim = simulate_session(SimConfig(pattern="running", fs_hz=200.0, n_strides=24, seed=5, legs=("left",)))
    create, batches = session_to_requests(sim, batch_size=400, patient_id=patient["id"], client_session_id="run-1")
    sid = c.post("/v1/sessions", json=create, headers=bearer(dev)).json()["id"]
    url = f"/v1/sessions/{sid}/compare"

    r = c.get(url, headers=bearer(clin))
    assert r.status_code == 409 and r.headers["content-type"].startswith("application/problem+json")
    for body in batches:
        assert api.upload(dev, sid, body).status_code in (200, 201)
    assert c.get(url, headers=bearer(clin)).status_code == 409  # still receiving
    assert c.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202

    assert c.get(url).status_code == 401
    assert c.get(url, headers=bearer(other_clin)).status_code == 404
    r = c.get(url + "?estimators=go,nope", headers=bearer(clin))
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "estimators"

    r = c.get(url, headers=bearer(dev))  # the device may read its patient's results
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["activity"] == "running" and not body["failed"]
    assert {"auto", "go", "cf", "kf", "ekf"} <= set(body["estimators"])
    leg = body["legs"]["left"]
    n = len(body["estimators"])
    assert len(leg["pairs"]) == n * (n - 1) // 2
    kf = leg["estimators"]["kf"]
    assert kf["n_strides"] >= 15
    assert 85.0 <= kf["peak_swing_flexion_deg"]["median"] <= 125.0
    assert leg["estimators"]["auto"]["stride_estimators"] == {"ekf": leg["estimators"]["auto"]["n_strides"]}
    pairs = {frozenset((p["a"], p["b"])): p for p in leg["pairs"]}
    # auto is the EKF for running, moved to the cycle-mean gravity's level (pipeline.cycle_gravity): the same curve,
    # a few degrees apart at most
    assert 0.0 < pairs[frozenset(("auto", "ekf"))]["rms_deg"] < 5.0
    kf_ekf = pairs[frozenset(("kf", "ekf"))]
    assert kf_ekf["rms_deg"] < 10.0 and kf_ekf["n_samples"] > 1000

    # the stored results of the same upload (the job runner's path) are the auto policy's
    assert run_queued(c.app.state.sessionmaker) == 1  # type: ignore[attr-defined]
    strides = c.get(f"/v1/sessions/{sid}/strides", headers=bearer(clin)).json()["strides"]
    assert len(strides) == leg["estimators"]["auto"]["n_strides"] and {s["estimator"] for s in strides} == {"ekf"}
    assert 85.0 <= float(np.median([s["peak_swing_flexion_deg"] for s in strides])) <= 125.0

    sub = c.get(url + "?estimators=kf,ekf", headers=bearer(clin)).json()
    assert sub["estimators"] == ["kf", "ekf"] and len(sub["legs"]["left"]["pairs"]) == 1

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("recomputed")

    monkeypatch.setattr(compare, "process_session", boom)  # the same content again: answered from memory
    again = c.get(url, headers=bearer(clin))
    assert again.status_code == 200 and again.json() == body
    fresh = c.get(url + "?estimators=go", headers=bearer(clin)).json()  # not cached: every estimator fails
    assert fresh["estimators"] == [] and fresh["failed"] == {"go": "recomputed"}


def test_the_estimator_set_is_normalised_for_the_cache() -> None:
    assert compare.requested_estimators("kf, go,kf") == ("kf", "go")
    assert compare.estimator_set(("kf", "go", "kf")) == compare.estimator_set(("go", "kf")) == ("go", "kf")
    assert compare.requested_estimators(None)[0] == "auto"


def test_a_session_longer_than_one_chunk_is_not_compared_in_the_api(api: Api) -> None:
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    create = {"patient_id": patient["id"], "client_session_id": "long-1", "started_at": "2026-11-30T08:00:00Z",
              "activity": "walking",
              "sensors": [{"sensor_id": "ls", "leg": "left", "segment": "shank", "sample_rate_hz": 1.0}]}
    sid = c.post("/v1/sessions", json=create, headers=bearer(dev)).json()["id"]
    # 40 minutes at 1 Hz without a hole: a span the workers process chunk by chunk
    still = {"gyro": [[0.0, 0.0, 0.0]] * 600, "acc": [[0.0, 0.0, 9.81]] * 600}
    for seq in range(4):
        body = {"sensor_id": "ls", "seq": seq, "t0_ms": seq * 600_000.0, **still}
        assert api.upload(dev, sid, body).status_code == 201
    assert c.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    r = c.get(f"/v1/sessions/{sid}/compare", headers=bearer(clin))
    assert r.status_code == 422 and r.headers["content-type"].startswith("application/problem+json")
    assert r.json()["type"].endswith("session-too-long-to-compare") and "40 min" in r.json()["detail"]
