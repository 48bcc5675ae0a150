"""Every route declares what it answers: a response model for JSON, a response class for the rest."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient
from jsonschema import Draft202012Validator
from openapi_spec_validator import validate
from pydantic import BaseModel

from server.app import create_app
from server.auth.schemas import ClinicianCreated, ClinicianIn, DeviceTokenCreated, DeviceTokenIn, MeOut
from server.calibrations.schemas import CalibrationIn
from server.config import Settings
from server.errors import Problem
from server.openapi import OPERATION_ID_RULE
from server.patients.schemas import PatientIn, PatientOut, PatientPatch
from server.results.schemas import KneeAngleOut
from server.sessions.schemas import BatchIn, BatchOut, SensorIn, SessionIn, SessionOut
from server.trends.schemas import TrendsOut


class _AnyText(str):
    def __eq__(self, other: object) -> bool:
        return isinstance(other, str) and bool(other)

    __hash__ = str.__hash__


ANY_TEXT = _AnyText()


def test_every_json_route_has_a_response_schema(tmp_path) -> None:  # noqa: ANN001
    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'x.sqlite'}", job_runner="manual"))
    spec = app.openapi()
    missing = []
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            for code, resp in op["responses"].items():
                content = resp.get("content") or {}
                if code.startswith("2") and "application/json" in content and not content["application/json"].get(
                        "schema"):
                    missing.append(f"{method.upper()} {path} {code}")
                if code.startswith("2") and not content and code != "204":
                    assert path.endswith(".csv"), f"{method.upper()} {path} {code} declares no content"
    assert missing == []
    trends = spec["paths"]["/v1/patients/{patient_id}/trends"]["get"]
    assert "activity" in {p["name"] for p in trends["parameters"]}


# --- the document as a contract clients are generated from -------------------------------------------------------

OPERATION_IDS = [
    "getHealth", "getMe", "createClinician", "listClinicians", "revokeToken",
    "createPatient", "listPatients", "getPatient", "updatePatient", "deletePatient",
    "createDeviceToken", "listDeviceTokens", "listPatientSessions",
    "createSession", "getSession", "uploadBatch", "completeSession", "reprocessSession",
    "listStrides", "getKneeAngle", "compareSession",
    "getPatientTrends", "getPatientSymmetry", "getPatientCompleteness", "listAttention", "exportStridesCsv",
    "getFhirBundle", "createCalibration", "listCalibrations", "getCalibration", "deleteCalibration",
]


@pytest.fixture(scope="module")
def spec(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    db = tmp_path_factory.mktemp("openapi") / "x.sqlite"
    app = create_app(Settings(database_url=f"sqlite:///{db}", job_runner="manual"))
    with TestClient(app) as client:
        r = client.get("/openapi.json")
    assert r.status_code == 200
    return r.json()


def _ops(spec: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [(m, p, op) for p, item in spec["paths"].items() for m, op in item.items()]


def _component(spec: dict[str, Any], schema: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    ref = schema.get("$ref") or next(s["$ref"] for s in schema["anyOf"] if "$ref" in s)
    name = ref.rsplit("/", 1)[-1]
    return name, spec["components"]["schemas"][name]


def test_served_document_is_valid_openapi(spec: dict[str, Any]) -> None:
    validate(spec)
    assert spec["openapi"].startswith("3.1")


def test_operation_ids_are_stable_unique_camel_case(spec: dict[str, Any]) -> None:
    ids = [op["operationId"] for _, _, op in _ops(spec)]
    assert len(ids) == len(set(ids))
    assert all(OPERATION_ID_RULE.match(i) for i in ids), ids
    assert sorted(ids) == sorted(OPERATION_IDS)


def test_bearer_scheme_on_every_v1_operation_and_none_on_health(spec: dict[str, Any]) -> None:
    assert spec["components"]["securitySchemes"]["bearerAuth"] == {
        "type": "http", "scheme": "bearer", "description": ANY_TEXT}
    for method, path, op in _ops(spec):
        if path.startswith("/v1/"):
            assert op.get("security") == [{"bearerAuth": []}], (method, path)
            assert {"401", "429"} <= set(op["responses"]), (method, path)
        else:
            assert "security" not in op and "401" not in op["responses"], (method, path)


def test_every_error_response_is_a_problem(spec: dict[str, Any]) -> None:
    assert "HTTPValidationError" not in json.dumps(spec) and "ValidationError" not in spec["components"]["schemas"]
    problem = spec["components"]["schemas"]["Problem"]
    assert {"type", "title", "status", "detail"} <= set(problem["required"])
    assert {"instance", "errors"} <= set(problem["properties"])
    n_errors = 0
    for method, path, op in _ops(spec):
        for code, resp in op["responses"].items():
            if code[0] in "45":
                n_errors += 1
                assert resp["content"] == {"application/problem+json": {
                    "schema": {"$ref": "#/components/schemas/Problem"}}}, (method, path, code)
                assert resp["description"], (method, path, code)
        has_input = bool(op.get("parameters")) or "requestBody" in op
        assert ("422" in op["responses"]) == has_input, (method, path)
        if any(p["in"] == "path" for p in op.get("parameters", [])):
            assert "404" in op["responses"], (method, path)
        if "requestBody" in op:
            assert {"400", "413", "415"} <= set(op["responses"]), (method, path)
    assert n_errors > 100
    by_id = {op["operationId"]: op for _, _, op in _ops(spec)}
    assert "409" in by_id["uploadBatch"]["responses"] and "409" in by_id["listStrides"]["responses"]
    assert "403" in by_id["createClinician"]["responses"] and "403" in by_id["getFhirBundle"]["responses"]
    assert "403" not in by_id["getSession"]["responses"]
    assert "503" in by_id["getHealth"]["responses"]
    assert by_id["getMe"]["responses"]["429"]["headers"]["Retry-After"]["schema"] == {"type": "integer"}


def test_csv_and_fhir_media_types_as_served(spec: dict[str, Any]) -> None:
    by_id = {op["operationId"]: op for _, _, op in _ops(spec)}
    assert set(by_id["exportStridesCsv"]["responses"]["200"]["content"]) == {"text/csv"}
    fhir = by_id["getFhirBundle"]["responses"]["200"]["content"]
    assert fhir == {"application/fhir+json": {"schema": {"$ref": "#/components/schemas/FhirBundleOut"}}}


REQUEST_MODELS = [CalibrationIn, ClinicianIn, PatientIn, PatientPatch, DeviceTokenIn, SessionIn, SensorIn, BatchIn]
RESPONSE_MODELS = [Problem, MeOut, ClinicianCreated, DeviceTokenCreated, PatientOut, SessionOut, BatchOut,
                   KneeAngleOut, TrendsOut]


def test_every_request_body_has_a_description_and_examples(spec: dict[str, Any]) -> None:
    bodies = set()
    for method, path, op in _ops(spec):
        if "requestBody" not in op:
            continue
        body = op["requestBody"]
        assert body.get("description"), (method, path)
        assert set(body["content"]) == {"application/json"}, (method, path)
        name, schema = _component(spec, body["content"]["application/json"]["schema"])
        assert schema.get("examples"), name
        bodies.add(name)
    assert bodies == {m.__name__ for m in REQUEST_MODELS} - {"SensorIn"}


@pytest.mark.parametrize("model", REQUEST_MODELS + RESPONSE_MODELS, ids=lambda m: m.__name__)
def test_examples_are_valid_for_model_and_schema(spec: dict[str, Any], model: type[BaseModel]) -> None:
    schema = spec["components"]["schemas"][model.__name__]
    validator = Draft202012Validator({**schema, "components": spec["components"]})
    assert schema["examples"]
    for example in schema["examples"]:
        model.model_validate(example)
        assert list(validator.iter_errors(example)) == []
