"""Test helpers for the HTTP API: an app on the test database, tokens, and contract request bodies."""

from __future__ import annotations

import gzip
import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy.engine import Engine

from server.app import create_app
from server.auth.service import issue_token
from server.config import Settings
from server.metadata import all_metadata

SENSORS_LEFT = [
    {"sensor_id": "L-thigh", "leg": "left", "segment": "thigh", "sample_rate_hz": 100, "gyro_unit": "deg/s",
     "acc_unit": "m/s2"},
    {"sensor_id": "L-shank", "leg": "left", "segment": "shank", "sample_rate_hz": 100, "gyro_unit": "deg/s",
     "acc_unit": "m/s2"},
]


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def batch_body(sensor_id: str, seq: int, n: int = 50, fs_hz: float = 100.0, *, t0_ms: float | None = None,
               seed: int = 0, timestamps: bool = False) -> dict[str, Any]:
    """A batch of ``n`` random samples starting where batch ``seq`` of equal batches would start."""
    rng = np.random.default_rng(abs(seed * 1000 + seq))
    t0 = seq * n * 1000.0 / fs_hz if t0_ms is None else t0_ms
    body: dict[str, Any] = {
        "sensor_id": sensor_id, "seq": seq, "t0_ms": t0,
        "gyro": np.round(rng.normal(0, 100, (n, 3)), 3).tolist(),
        "acc": np.round(rng.normal(0, 9.81, (n, 3)), 3).tolist(),
    }
    if timestamps:
        body["timestamps_ms"] = (t0 + np.arange(n) * 1000.0 / fs_hz).tolist()
    return body


def gzip_json(body: Any) -> bytes:
    return gzip.compress(json.dumps(body).encode())


def count_rows(engine: Engine) -> dict[str, int]:
    """Rows per table of every model module (core, trends, ...)."""
    out = {}
    with engine.connect() as conn:
        for table in all_metadata().sorted_tables:
            out[table.name] = conn.execute(select(func.count()).select_from(table)).scalar_one()
    return out


@dataclass
class Api:
    client: TestClient
    settings: Settings
    admin: str

    @property
    def engine(self) -> Engine:
        return self.client.app.state.engine  # type: ignore[attr-defined]

    def clinician(self, name: str = "Dr. Test") -> tuple[str, str]:
        r = self.client.post("/v1/clinicians", json={"name": name}, headers=bearer(self.admin))
        assert r.status_code == 201, r.text
        return r.json()["id"], r.json()["token"]

    def patient(self, token: str, **body: Any) -> dict[str, Any]:
        r = self.client.post("/v1/patients", json=body, headers=bearer(token))
        assert r.status_code == 201, r.text
        return r.json()

    def device(self, token: str, patient_id: str) -> str:
        r = self.client.post(f"/v1/patients/{patient_id}/device-tokens", headers=bearer(token))
        assert r.status_code == 201, r.text
        return r.json()["token"]

    def session(self, token: str, patient_id: str, client_session_id: str = "app-1",
                sensors: list[dict[str, Any]] | None = None, activity: str = "walking") -> dict[str, Any]:
        body = {"patient_id": patient_id, "client_session_id": client_session_id,
                "started_at": "2026-11-21T09:30:00+01:00", "activity": activity,
                "sensors": sensors or SENSORS_LEFT}
        r = self.client.post("/v1/sessions", json=body, headers=bearer(token))
        assert r.status_code in (200, 201), r.text
        return r.json()

    def upload(self, token: str, session_id: str, body: dict[str, Any], *, gzipped: bool = False):  # noqa: ANN201
        if gzipped:
            headers = {**bearer(token), "Content-Encoding": "gzip", "Content-Type": "application/json"}
            return self.client.post(f"/v1/sessions/{session_id}/batches", content=gzip_json(body), headers=headers)
        return self.client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=bearer(token))

    def setup_device_session(self) -> tuple[str, str, dict[str, Any]]:
        """Clinician token, device token and a fresh receiving session of a new patient."""
        _, clin = self.clinician()
        patient = self.patient(clin)
        dev = self.device(clin, patient["id"])
        return clin, dev, self.session(dev, patient["id"])


@contextmanager
def open_api(settings: Settings) -> Iterator[Api]:
    app = create_app(settings)
    with app.state.sessionmaker() as db:
        _, admin = issue_token(db, role="admin", name="test admin")
        db.commit()
    # raise_server_exceptions=False: a 500 must reach the test as the problem document a client would get.
    with TestClient(app, raise_server_exceptions=False) as client:
        yield Api(client=client, settings=settings, admin=admin)
