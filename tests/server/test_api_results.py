"""Results end to end: a simulated session uploaded over HTTP, processed by the job code, read back."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from pipeline.simulate import SimConfig, simulate_session
from server.config import Settings
from server.processing.jobs import run_queued
from server.results.service import minmax_indices
from server.simulate_cli import arrange_batches, session_to_requests
from tests.server.helpers import Api, bearer, count_rows, open_api


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def test_minmax_downsampling_keeps_extremes_and_gaps() -> None:
    t = np.arange(10_000) / 100.0
    angle = 30 + 30 * np.sin(2 * np.pi * t / 1.1)
    angle[4000:4500] = np.nan  # a 5 s gap, far longer than a bucket
    idx = minmax_indices(angle, 400)
    assert len(idx) <= 400 and np.all(np.diff(idx) > 0)
    assert np.nanmax(angle[idx]) == np.nanmax(angle) and np.nanmin(angle[idx]) == np.nanmin(angle)
    assert np.isnan(angle[idx]).any()  # the gap still breaks the line
    assert np.array_equal(minmax_indices(angle[:300], 400), np.arange(300))


def _upload_simulated(api: Api, dev: str, patient_id: str, cfg: SimConfig | None = None) -> tuple[str, object]:
    sim = simulate_session(cfg or SimConfig(n_strides=24, seed=3, legs=("left",)))
    create, batches = session_to_requests(sim, batch_size=100, patient_id=patient_id, client_session_id="sim-1")
    sess = api.client.post("/v1/sessions", json=create, headers=bearer(dev))
    assert sess.status_code == 201, sess.text
    sid = sess.json()["id"]
    for i, body in enumerate(arrange_batches(batches, shuffle=True, duplicate_fraction=0.1, seed=1)):
        r = api.upload(dev, sid, body, gzipped=i % 2 == 0)
        assert r.status_code in (200, 201), r.text
    got = api.client.get(f"/v1/sessions/{sid}", headers=bearer(dev)).json()
    for sensor in ("L-thigh", "L-shank"):
        expected = sum(len(b["gyro"]) for b in batches if b["sensor_id"] == sensor)
        assert got["received"][sensor]["samples"] == expected
    return sid, sim


def test_simulated_session_strides_and_knee_angle(api: Api) -> None:
    c = api.client
    clin_id, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    sid, sim = _upload_simulated(api, dev, patient["id"])
    assert c.get(f"/v1/sessions/{sid}/strides", headers=bearer(dev)).status_code == 409
    assert c.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    assert c.get(f"/v1/sessions/{sid}/knee-angle", headers=bearer(dev)).status_code == 409
    assert run_queued(c.app.state.sessionmaker) == 1  # type: ignore[attr-defined]

    sess = c.get(f"/v1/sessions/{sid}", headers=bearer(dev)).json()
    assert sess["status"] == "done", sess["error"]
    assert sess["algorithm_version"] and sess["summary"]["legs"]["left"]["n_strides"] > 0

    strides = c.get(f"/v1/sessions/{sid}/strides?leg=left", headers=bearer(clin)).json()["strides"]
    assert len(strides) == sess["summary"]["legs"]["left"]["n_strides"]
    assert c.get(f"/v1/sessions/{sid}/strides?leg=right", headers=bearer(clin)).json()["strides"] == []
    for s in strides:
        assert s["leg"] == "left" and s["t_start_s"] < s["t_end_s"] and s["estimator"]
        assert {"stance_time_s", "swing_time_s", "quality_reasons", "quality"} <= set(s)
    assert [s["index"] for s in strides] == sorted(s["index"] for s in strides)
    truth = [s.peak_swing_flexion_deg for s in sim.truth["left"].strides if s.steady]
    measured = [s["peak_swing_flexion_deg"] for s in strides if s["peak_swing_flexion_deg"] is not None]
    assert abs(np.median(measured) - np.median(truth)) < 15.0

    full = c.get(f"/v1/sessions/{sid}/knee-angle?leg=left&max_points=200000", headers=bearer(dev)).json()
    small = c.get(f"/v1/sessions/{sid}/knee-angle?leg=left&max_points=300", headers=bearer(dev)).json()
    assert full["downsampling"] == "none" and len(full["t_s"]) == full["n_total"] > 300
    assert small["downsampling"] == "minmax" and len(small["t_s"]) <= 300
    assert len(small["t_s"]) == len(small["angle_deg"]) == len(small["estimator"])
    assert np.all(np.diff(small["t_s"]) > 0)
    finite_full = [a for a in full["angle_deg"] if a is not None]
    finite_small = [a for a in small["angle_deg"] if a is not None]
    assert max(finite_small) == max(finite_full) and min(finite_small) == min(finite_full)
    assert {e for e in full["estimator"] if e} <= {s["estimator"] for s in strides} | {"cf", "go"}
    assert all(e is None for a, e in zip(full["angle_deg"], full["estimator"], strict=True) if a is None)
    window = c.get(f"/v1/sessions/{sid}/knee-angle?max_points=200000&start_s=5&end_s=10",
                   headers=bearer(dev)).json()
    assert window["t_s"][0] >= 5 and window["t_s"][-1] <= 10 and window["n_total"] == pytest.approx(500, abs=2)
    assert full["withheld"] is None and window["withheld"] is None
    assert full["not_worn_s"] == [] and window["not_worn_s"] == []
    assert c.get(f"/v1/sessions/{sid}/knee-angle?leg=right", headers=bearer(dev)).status_code == 404

    # Reprocess: device may not; the clinician may; results are replaced, not duplicated.
    assert c.post(f"/v1/sessions/{sid}/reprocess", headers=bearer(dev)).status_code == 403
    r = c.post(f"/v1/sessions/{sid}/reprocess", headers=bearer(clin))
    assert r.status_code == 202 and r.json()["status"] == "queued"
    assert run_queued(c.app.state.sessionmaker) == 1  # type: ignore[attr-defined]
    again = c.get(f"/v1/sessions/{sid}/strides", headers=bearer(clin)).json()["strides"]
    assert [s["t_start_s"] for s in again] == [s["t_start_s"] for s in strides]
    listed = c.get(f"/v1/patients/{patient['id']}/sessions", headers=bearer(clin)).json()["items"]
    assert [s["id"] for s in listed] == [sid] and listed[0]["status"] == "done"

    # Deleting the patient removes the processed session too, including the trend summaries built from it.
    before = count_rows(api.engine)
    assert before["strides"] > 0 and before["knee_angle_traces"] == 1
    assert all(n > 0 for table, n in before.items() if table.startswith("trend_"))
    assert c.delete(f"/v1/patients/{patient['id']}", headers=bearer(clin)).status_code == 204
    after = count_rows(api.engine)
    assert after.pop("clinicians") == 1 and after.pop("tokens") == 2  # admin + clinician; the device's is gone
    assert all(n == 0 for n in after.values()), after


def test_an_exercise_session_without_gait_shows_no_knee_angle(api: Api) -> None:
    """Seated knee extensions alone: the knee axes and zero have no gait to be learned from, so the trace is
    withheld (every angle null, ``withheld`` says why) and the session's warnings say so, instead of a seated knee
    read tens of degrees off."""
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    cfg = SimConfig(seed=1, legs=("left",), walking=False, activities=("seated_extension",), move_reps=4)
    sid, _ = _upload_simulated(api, dev, patient["id"], cfg)
    assert c.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    assert run_queued(c.app.state.sessionmaker) == 1  # type: ignore[attr-defined]
    sess = c.get(f"/v1/sessions/{sid}", headers=bearer(clin)).json()
    assert sess["status"] == "done", sess["error"]
    assert sess["summary"]["legs"]["left"]["n_strides"] == 0
    assert any("no knee angle" in w for w in sess["summary"]["warnings"])
    trace = c.get(f"/v1/sessions/{sid}/knee-angle?leg=left&max_points=500", headers=bearer(clin)).json()
    assert trace["withheld"] == "no_gait" and trace["n_total"] > 1000
    assert all(a is None for a in trace["angle_deg"]) and all(e is None for e in trace["estimator"])


def test_sensors_taken_off_mid_session_show_no_angle_there(api: Api) -> None:
    """The left leg's sensors are laid on a table half-way while the person walks on: the knee-angle response says
    when (``not_worn_s``), its angles there are null, and the session warns."""
    c = api.client
    _, clin = api.clinician()
    patient = api.patient(clin)
    dev = api.device(clin, patient["id"])
    cfg = SimConfig(seed=0, duration_s=90.0, bout_strides=12, off_body="left")
    sid, sim = _upload_simulated(api, dev, patient["id"], cfg)
    assert c.post(f"/v1/sessions/{sid}/complete", headers=bearer(dev)).status_code == 202
    assert run_queued(c.app.state.sessionmaker) == 1  # type: ignore[attr-defined]
    sess = c.get(f"/v1/sessions/{sid}", headers=bearer(clin)).json()
    assert sess["status"] == "done", sess["error"]
    assert any("not on the leg" in w for w in sess["summary"]["warnings"])
    off_s = sim.info["sensors"]["L-thigh"]["off_body"]["at_s"]
    left = c.get(f"/v1/sessions/{sid}/knee-angle?leg=left&max_points=200000", headers=bearer(clin)).json()
    (t0, t1), = left["not_worn_s"]
    assert off_s - 3.0 < t0 <= off_s + 0.5 and t1 > sim.duration_s - 1.0
    shown = [t for t, a in zip(left["t_s"], left["angle_deg"], strict=True) if a is not None]
    assert shown and max(shown) < off_s + 0.5
    right = c.get(f"/v1/sessions/{sid}/knee-angle?leg=right&max_points=500", headers=bearer(clin)).json()
    assert right["not_worn_s"] == [] and right["withheld"] is None
