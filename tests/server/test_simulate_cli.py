"""`gaitmon simulate`: request building, file output, and the upload loop against a fake server (no database)."""

from __future__ import annotations

import argparse
import gzip
import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from gaitmon.client import Client
from pipeline.simulate import SimConfig, simulate_session
from server.sessions.schemas import BatchIn, SessionIn
from server.simulate_cli import arrange_batches, register, session_to_requests, upload


@pytest.fixture(scope="module")
def sim():
    return simulate_session(SimConfig(seed=3, n_strides=8, packet_loss=0.05, outages_per_min=5.0))


def test_requests_match_the_contract_and_keep_every_sample(sim) -> None:
    create, batches = session_to_requests(sim, batch_size=40, patient_id="p1")
    SessionIn.model_validate(create)
    assert {s["sensor_id"] for s in create["sensors"]} == {s.sensor_id for s in sim.streams}
    for stream in sim.streams:
        mine = sorted((b for b in batches if b["sensor_id"] == stream.sensor_id), key=lambda b: b["seq"])
        assert [b["seq"] for b in mine] == list(range(len(mine)))
        assert all(1 <= len(b["gyro"]) <= 40 for b in mine)
        t_ms = np.concatenate([b["timestamps_ms"] for b in mine])
        assert np.allclose(t_ms, stream.t_s * 1000, atol=1e-3)
        assert np.allclose(np.concatenate([b["gyro"] for b in mine]), stream.gyr, atol=1e-3)
        assert np.allclose(np.concatenate([b["acc"] for b in mine]), stream.acc, atol=1e-4)
        for b in mine:
            BatchIn.model_validate(b)
            # a batch never spans lost packets, so t0 + i/fs is also right
            implied = b["t0_ms"] + np.arange(len(b["gyro"])) * 1000 / stream.fs_hz
            assert np.allclose(implied, b["timestamps_ms"], atol=2e-3)
    t0s = [b["t0_ms"] for b in batches]
    assert t0s == sorted(t0s)


def test_arrange_batches_shuffles_and_duplicates() -> None:
    batches = [{"sensor_id": "a", "seq": i} for i in range(100)]
    out = arrange_batches(batches, shuffle=True, duplicate_fraction=0.2, seed=1)
    assert len(out) == 120
    assert {b["seq"] for b in out} == set(range(100))
    assert [b["seq"] for b in out] != list(range(100)) + [b["seq"] for b in out[100:]]
    assert arrange_batches(batches) == batches


def test_upload_sends_gzip_retries_network_errors_and_completes(sim, monkeypatch: pytest.MonkeyPatch) -> None:
    create, batches = session_to_requests(sim, batch_size=100, patient_id="p1")
    stored: dict[tuple[str, int], dict] = {}
    calls = {"fail": 2, "complete": 0}

    def session(status: str) -> dict:
        return {"id": "s1", "patient_id": "p1", "client_session_id": create["client_session_id"],
                "started_at": create["started_at"], "activity": create["activity"], "status": status,
                "created_at": create["started_at"]}

    def handler(request: httpx.Request) -> httpx.Response:
        path = request.url.path
        if path == "/v1/sessions":
            return httpx.Response(201, json=session("receiving"))
        if path == "/v1/sessions/s1/batches":
            if calls["fail"] > 0:  # the first attempts die on the network
                calls["fail"] -= 1
                raise httpx.ConnectError("boom", request=request)
            assert request.headers["content-encoding"] == "gzip"
            body = json.loads(gzip.decompress(request.content))
            key = (body["sensor_id"], body["seq"])
            dup = key in stored
            stored[key] = body
            return httpx.Response(200 if dup else 201, json={"sensor_id": key[0], "seq": key[1],
                                                             "samples": len(body["gyro"]), "duplicate": dup})
        if path == "/v1/sessions/s1/complete":
            calls["complete"] += 1
            return httpx.Response(202, json=session("queued"))
        return httpx.Response(404)

    order = arrange_batches(batches, shuffle=True, duplicate_fraction=0.3, seed=2)
    msgs: list[str] = []
    with Client("http://test", "t", transport=httpx.MockTransport(handler)) as client:
        monkeypatch.setattr("gaitmon.client.sync.time.sleep", lambda s: None)  # no real back-off waits
        sid = upload(client, create, order, concurrency=2, progress=msgs.append)
    assert sid == "s1"
    assert len(stored) == len(batches)
    assert calls["complete"] == 1 and calls["fail"] == 0
    assert any("duplicates acknowledged" in m for m in msgs)


def test_cli_writes_session_file(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    out = tmp_path / "s.json"
    args = parser.parse_args(["simulate", "--pattern", "crouch", "--minutes", "0.5", "--fs", "50", "--seed", "4",
                              "--out", str(out), "--started-at", "2026-11-21T09:30:00+00:00"])
    assert args.func(args) == 0
    doc = json.loads(out.read_text())
    assert doc["session"]["started_at"] == "2026-11-21T09:30:00+00:00"
    assert all(s["sample_rate_hz"] == 50 for s in doc["session"]["sensors"])
    assert len(doc["batches"]) > 20
    assert doc["truth"]["left"]["min_flexion_deg_median"] > 18  # crouch never extends
    # no destination given: a usage error, not a crash
    bad = parser.parse_args(["simulate", "--minutes", "0.2"])
    assert bad.func(bad) == 2
