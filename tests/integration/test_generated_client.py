"""A client generated from the served /openapi.json walks the whole contract against a real server.

The server runs as ``gaitmon serve`` (SQLite in a temporary directory, embedded jobs). ``openapi-python-client``
generates a package from the document the server serves; every call below goes through that package, never through
hand-written HTTP. A response hook checks every answer against the document: its status is documented for the
operation, its media type is the documented one and its JSON body validates against the documented schema. The
test ends by asserting that every operation of the document was called.
"""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from types import ModuleType
from typing import Any

import httpx
import pytest
from jsonschema import Draft202012Validator
from openapi_spec_validator import validate

from pipeline.simulate import SimConfig, simulate_session
from server.auth.service import issue_token
from server.db import make_engine, make_sessionmaker
from server.enums import Role
from server.simulate_cli import session_to_requests
from tests.integration.conftest import free_port, server_env
from tests.integration.test_contract_walk import Proc, processes, wait_healthy

PACKAGE = "gaitmon_api_client"
BATCH_SAMPLES = 1000
WAIT_S = 60.0


def generate_client(spec_path: Path, out_dir: Path) -> ModuleType:
    """Generate the client package with the openapi-python-client command and import it."""
    config = out_dir / "config.yml"
    config.write_text(f"package_name_override: {PACKAGE}\npost_hooks: []\n")
    command = Path(sys.executable).with_name("openapi-python-client")
    res = subprocess.run([str(command), "generate", "--path", str(spec_path), "--config", str(config),
                          "--meta", "none", "--output-path", str(out_dir / PACKAGE)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    # The generator reports what it could not translate as warnings but still exits 0: none may occur.
    assert "Warning" not in res.stdout + res.stderr, res.stdout + res.stderr
    sys.path.insert(0, str(out_dir))
    return importlib.import_module(PACKAGE)


@pytest.fixture
def generated_package_dir(tmp_path: Path) -> Iterator[Path]:
    out = tmp_path / "generated"
    out.mkdir()
    yield out
    if str(out) in sys.path:
        sys.path.remove(str(out))
    for name in [m for m in sys.modules if m == PACKAGE or m.startswith(PACKAGE + ".")]:
        del sys.modules[name]


class ContractCheck:
    """An httpx response hook: every response must be one the document declares."""

    def __init__(self, spec: dict[str, Any]) -> None:
        self.spec = spec
        self.routes = [(re.compile("^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(path)) + "$"), item)
                       for path, item in spec["paths"].items()]
        self.called: set[str] = set()
        self.failures: list[str] = []

    def __call__(self, response: httpx.Response) -> None:
        response.read()
        method, path = response.request.method.lower(), response.request.url.path
        item = next((item for rx, item in self.routes if rx.match(path)), None)
        if item is None or method not in item:
            self.failures.append(f"{method} {path}: not in the document")
            return
        op = item[method]
        self.called.add(op["operationId"])
        where = f"{op['operationId']} -> {response.status_code}"
        declared = op["responses"].get(str(response.status_code))
        if declared is None:
            self.failures.append(f"{where}: status not documented")
            return
        content = declared.get("content") or {}
        if response.status_code == 204 or not content:
            return
        media = response.headers.get("content-type", "").split(";")[0].strip()
        if media not in content:
            self.failures.append(f"{where}: served {media!r}, documented {sorted(content)}")
            return
        if media.endswith("json"):
            schema = {**content[media]["schema"], "components": self.spec["components"]}
            errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message[:200]}"
                      for e in Draft202012Validator(schema).iter_errors(response.json())]
            if errors:
                self.failures.append(f"{where}: body does not match the schema: {errors[:5]}")


def _ok(resp: Any, status: int) -> Any:
    assert resp.status_code == status, (resp.status_code, resp.content[:500])
    return resp.parsed


def _wait_done(client: Any, session_id: str) -> Any:
    get_session = op("sessions_and_upload", "get_session")
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        session = _ok(get_session.sync_detailed(session_id, client=client), 200)
        assert session.status.value != "failed", session.error
        if session.status.value == "done":
            return session
        time.sleep(0.2)
    raise AssertionError(f"session {session_id} not done within {WAIT_S} s")


def test_generated_client_walks_the_contract(tmp_path: Path, generated_package_dir: Path) -> None:
    env = server_env(tmp_path, None)
    port = free_port()
    base_url = f"http://127.0.0.1:{port}"
    with processes() as procs:
        server = Proc(["serve", "--port", str(port)], env, tmp_path, tmp_path / "serve.log")
        procs.append(server)
        with httpx.Client(base_url=base_url) as plain:
            wait_healthy(plain, server)
            served = plain.get("/openapi.json")
        assert served.status_code == 200
        spec = served.json()
        validate(spec)
        spec_path = tmp_path / "openapi.json"
        spec_path.write_bytes(served.content)
        gen = generate_client(spec_path, generated_package_dir)
        engine = make_engine(f"sqlite:///{tmp_path / 'data' / 'gaitmon.sqlite'}")
        with make_sessionmaker(engine)() as db:
            _, admin_token = issue_token(db, role=Role.admin, name="walk")
            db.commit()
        engine.dispose()
        check = ContractCheck(spec)
        walk(gen, base_url, admin_token, check)
        assert check.failures == []
        assert check.called == {op["operationId"] for item in spec["paths"].values() for op in item.values()}


def op(group: str, name: str) -> ModuleType:
    """The generated module of one operation (``api/<tag>/<operation id in snake_case>.py``)."""
    return importlib.import_module(f"{PACKAGE}.api.{group}.{name}")


def walk(gen: ModuleType, base_url: str, admin_token: str, check: ContractCheck) -> None:
    m = importlib.import_module(f"{PACKAGE}.models")
    hooks = {"response": [check]}

    def client(token: str) -> Any:
        return gen.AuthenticatedClient(base_url=base_url, token=token, raise_on_unexpected_status=True,
                                       httpx_args={"event_hooks": hooks}, timeout=httpx.Timeout(30.0))

    anonymous = gen.Client(base_url=base_url, raise_on_unexpected_status=True, httpx_args={"event_hooks": hooks})
    assert _ok(op("health", "get_health").sync_detailed(client=anonymous), 200).status == "ok"
    problem = _ok(op("clinicians_and_tokens", "get_me").sync_detailed(client=client("gm_wrong")), 401)
    assert isinstance(problem, m.Problem) and problem.status == 401

    admin = client(admin_token)
    assert _ok(op("clinicians_and_tokens", "get_me").sync_detailed(client=admin), 200).role == m.Role.ADMIN
    created = _ok(op("clinicians_and_tokens", "create_clinician").sync_detailed(
        client=admin, body=m.ClinicianIn(name="Dr Walk", email="walk@example.org")), 201)
    assert created.token.startswith("gm_")
    clinicians = _ok(op("clinicians_and_tokens", "list_clinicians").sync_detailed(client=admin), 200)
    assert [c.id for c in clinicians] == [created.id]

    clin = client(created.token)
    patient = _ok(op("patients", "create_patient").sync_detailed(client=clin, body=m.PatientIn(
        external_id="MRN-0042", display_name="Walk Patient", affected_leg=m.Leg.LEFT, timezone="Europe/Berlin")),
        201)
    assert _ok(op("patients", "list_patients").sync_detailed(client=clin), 200).items[0].id == patient.id
    assert _ok(op("patients", "get_patient").sync_detailed(patient.id, client=clin), 200).external_id == "MRN-0042"
    patched = _ok(op("patients", "update_patient").sync_detailed(patient.id, client=clin,
                                                                   body=m.PatientPatch(display_name="W. Patient")), 200)
    assert patched.display_name == "W. Patient" and patched.timezone == "Europe/Berlin"
    device_token = _ok(op("patients", "create_device_token").sync_detailed(
        patient.id, client=clin, body=m.DeviceTokenIn(name="phone")), 201)
    tokens = _ok(op("patients", "list_device_tokens").sync_detailed(patient.id, client=clin), 200)
    assert [t.id for t in tokens] == [device_token.token_id]

    calibration = _ok(op("patients", "create_calibration").sync_detailed(patient.id, client=clin, body=m.CalibrationIn(
        leg=m.Leg.LEFT, standing_knee_deg=6.0, measured_at=datetime(2026, 11, 20, 9, tzinfo=UTC),
        method=m.CalibrationMethod.GONIOMETER)), 201)
    listed = _ok(op("patients", "list_calibrations").sync_detailed(patient.id, client=clin), 200)
    assert [c.id for c in listed.items] == [calibration.id]
    got = _ok(op("patients", "get_calibration").sync_detailed(patient.id, calibration.id, client=clin), 200)
    assert got.standing_knee_deg == 6.0

    device = client(device_token.token)
    sim = simulate_session(SimConfig(n_strides=24, seed=3))
    body, batches = session_to_requests(sim, batch_size=BATCH_SAMPLES, patient_id=patient.id)
    session = _ok(op("sessions_and_upload", "create_session").sync_detailed(
        client=device, body=m.SessionIn.from_dict(body)), 201)
    assert session.status.value == "receiving"
    for b in batches:
        ack = _ok(op("sessions_and_upload", "upload_batch").sync_detailed(
            session.id, client=device, body=m.BatchIn.from_dict(b)), 201)
        assert ack.samples == len(b["gyro"]) and not ack.duplicate
    replay = _ok(op("sessions_and_upload", "upload_batch").sync_detailed(
        session.id, client=device, body=m.BatchIn.from_dict(batches[0])), 200)
    assert replay.duplicate
    short = {**batches[0], "seq": 10_000, "acc": batches[0]["acc"][:-1]}
    problem = _ok(op("sessions_and_upload", "upload_batch").sync_detailed(
        session.id, client=device, body=m.BatchIn.from_dict(short)), 422)
    assert problem.errors and problem.errors[0].message
    problem = _ok(op("sessions_and_upload", "reprocess_session").sync_detailed(session.id, client=device), 403)
    assert problem.status == 403

    _ok(op("sessions_and_upload", "complete_session").sync_detailed(session.id, client=device), 202)
    done = _wait_done(device, session.id)
    assert done.summary is not None
    page = _ok(op("patients", "list_patient_sessions").sync_detailed(patient.id, client=clin), 200)
    assert [s.id for s in page.items] == [session.id]

    strides = _ok(op("results", "list_strides").sync_detailed(session.id, client=clin), 200).strides
    n_left = sum(s.leg == m.Leg.LEFT for s in strides)
    assert n_left > 10 and len(strides) - n_left > 10
    trace = _ok(op("results", "get_knee_angle").sync_detailed(session.id, client=device, leg=m.Leg.LEFT,
                                                               max_points=400), 200)
    assert 100 < len(trace.t_s) <= 400 and len(trace.angle_deg) == len(trace.t_s)
    compared = _ok(op("results", "compare_session").sync_detailed(session.id, client=clin, estimators="go"), 200)
    assert "go" in compared.estimators

    _ok(op("sessions_and_upload", "reprocess_session").sync_detailed(session.id, client=clin), 202)
    _wait_done(clin, session.id)
    again = _ok(op("results", "list_strides").sync_detailed(session.id, client=clin), 200).strides
    assert [s.peak_swing_flexion_deg for s in again] == [s.peak_swing_flexion_deg for s in strides]

    trends = _ok(op("trends", "get_patient_trends").sync_detailed(patient.id, client=clin, leg="left"), 200)
    assert sum(b.n_strides for b in trends.buckets) > 0
    symmetry = _ok(op("trends", "get_patient_symmetry").sync_detailed(patient.id, client=clin), 200)
    assert symmetry.affected_leg == "left"
    completeness = _ok(op("trends", "get_patient_completeness").sync_detailed(patient.id, client=clin), 200)
    assert completeness.strides_total > 0
    attention = _ok(op("trends", "list_attention").sync_detailed(client=clin), 200)
    assert attention.n_patients == 1
    bundle = _ok(op("trends", "get_fhir_bundle").sync_detailed(patient.id, client=clin), 200)
    assert bundle.resource_type == "Bundle" and bundle.entry
    csv = op("trends", "export_strides_csv").sync_detailed(patient.id, client=clin)
    assert csv.status_code == 200
    rows = csv.content.decode().strip().splitlines()
    assert rows[0].startswith("session_id,") and len(rows) - 1 == len(again)

    _ok(op("patients", "delete_calibration").sync_detailed(patient.id, calibration.id, client=clin), 204)
    _ok(op("clinicians_and_tokens", "revoke_token").sync_detailed(device_token.token_id, client=clin), 204)
    assert _ok(op("sessions_and_upload", "get_session").sync_detailed(session.id, client=device), 401).status == 401
    _ok(op("patients", "delete_patient").sync_detailed(patient.id, client=clin), 204)
    assert _ok(op("patients", "get_patient").sync_detailed(patient.id, client=clin), 404).status == 404
