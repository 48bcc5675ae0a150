"""Trends HTTP endpoints: parameters, access rules, CSV and FHIR exports (SQLite and PostgreSQL)."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from fhir.resources.R4B.bundle import Bundle

from server.config import Settings
from tests.server.helpers import Api, bearer, open_api
from tests.support.seed import add_session

T0 = datetime(2026, 10, 5, 9, 0, tzinfo=UTC)


@pytest.fixture
def api(settings: Settings) -> Iterator[Api]:
    with open_api(settings) as a:
        yield a


def _seeded(api: Api, **patient: object) -> tuple[str, dict]:
    _, clin = api.clinician()
    p = api.patient(clin, affected_leg="left", timezone="Europe/Berlin", **patient)
    with api.client.app.state.sessionmaker() as db:  # type: ignore[attr-defined]
        for k in range(3):
            peaks = np.where(np.arange(30) % 2 == 0, 40 + 5 * k - 1, 40 + 5 * k + 1).astype(float)
            peaks[0] = 170.0  # implausible: excluded and counted
            add_session(db, p["id"], T0 + timedelta(days=7 * k),
                        {"left": {"n": 30, "peak_swing_flexion_deg": peaks},
                         "right": {"n": 30, "peak_swing_flexion_deg": 60.0, "quality": 0.9}})
        db.commit()
    return clin, p


def test_trends_contract_shape_and_values(api: Api) -> None:
    clin, p = _seeded(api)
    r = api.client.get(f"/v1/patients/{p['id']}/trends", params={"metric": "peak_swing_flexion_deg"},
                       headers=bearer(clin))
    assert r.status_code == 200, r.text
    body = r.json()
    assert {"metric", "unit", "leg", "buckets", "trend", "change"} <= set(body)
    assert body["leg"] == "left"  # the affected leg by default
    assert {"start", "n_sessions", "n_strides", "mean", "sd", "median"} <= set(body["buckets"][0])
    assert {"slope_per_week", "ci95", "n"} <= set(body["trend"])
    assert {"baseline", "latest", "delta", "mdc", "significant"} <= set(body["change"])
    assert [b["n_excluded"] for b in body["buckets"]] == [1, 1, 1]
    assert [b["n_strides"] for b in body["buckets"]] == [29, 29, 29]
    assert body["buckets"][0]["start"] == "2026-10-05T00:00:00+02:00"  # Berlin summer time
    means = [b["mean"] for b in body["buckets"]]
    assert means[0] < means[1] < means[2]
    assert body["trend"]["slope_per_week"] > 0 and body["change"]["significant"] is True
    right = api.client.get(f"/v1/patients/{p['id']}/trends", params={"leg": "right", "bucket": "week"},
                           headers=bearer(clin)).json()
    assert [b["mean"] for b in right["buckets"]] == [60.0, 60.0, 60.0]
    assert right["change"]["significant"] is False


@pytest.mark.parametrize("params, field", [
    ({"metric": "knee_magic"}, "metric"), ({"leg": "middle"}, "leg"), ({"bucket": "month"}, "bucket"),
    ({"from": "2026-10-20", "to": "2026-10-01"}, "from"), ({"from": "yesterday"}, "from"),
    ({"method": "spline"}, "method"),
])
def test_invalid_parameters_are_422_problems(api: Api, params: dict, field: str) -> None:
    clin, p = _seeded(api)
    r = api.client.get(f"/v1/patients/{p['id']}/trends", params=params, headers=bearer(clin))
    assert r.status_code == 422
    assert r.headers["content-type"].startswith("application/problem+json")
    assert field in [e["field"] for e in r.json()["errors"]]


def test_access_rules(api: Api) -> None:
    clin, p = _seeded(api)
    _, stranger = api.clinician("Dr. Other")
    device = api.device(clin, p["id"])
    base = f"/v1/patients/{p['id']}"
    assert api.client.get(f"{base}/trends", headers=bearer(stranger)).status_code == 404
    assert api.client.get(f"{base}/trends").status_code == 401
    # The patient's app may show the patient's own progress, but not export or see other patients.
    assert api.client.get(f"{base}/trends", headers=bearer(device)).status_code == 200
    assert api.client.get(f"{base}/completeness", headers=bearer(device)).status_code == 200
    assert api.client.get(f"{base}/strides.csv", headers=bearer(device)).status_code == 403
    assert api.client.get(f"{base}/fhir", headers=bearer(device)).status_code == 403
    assert api.client.get("/v1/attention", headers=bearer(device)).status_code == 403
    assert api.client.get(f"{base}/fhir", headers=bearer(stranger)).status_code == 404


def test_strides_csv_parses_and_marks_exclusions(api: Api) -> None:
    clin, p = _seeded(api)
    r = api.client.get(f"/v1/patients/{p['id']}/strides.csv", params={"from": "2026-10-05", "to": "2026-10-12"},
                       headers=bearer(clin))
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/csv")
    assert "attachment" in r.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert len(rows) == 120  # two sessions (5 and 12 October, local) x two legs x 30 strides
    assert {row["leg"] for row in rows} == {"left", "right"}
    bad = [row for row in rows if row["included"] == "0"]
    assert len(bad) == 2 and all("implausible:peak_swing_flexion_deg" in row["excluded_because"] for row in bad)
    assert float(rows[0]["duration_s"]) == pytest.approx(1.1)
    assert rows[0]["started_at"].endswith("+02:00")


def test_fhir_bundle_validates_as_r4(api: Api) -> None:
    clin, p = _seeded(api)
    r = api.client.get(f"/v1/patients/{p['id']}/fhir", params={"metric": ["peak_swing_flexion_deg", "rom_deg"]},
                       headers=bearer(clin))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("application/fhir+json")
    bundle = Bundle.model_validate(r.json())
    assert bundle.type == "collection"
    obs = [e.resource for e in bundle.entry if e.resource.get_resource_type() == "Observation"]
    assert len(obs) == 3 * 2 * 2  # days x legs x metrics
    peak_left = [o for o in obs if o.code.coding[0].code == "peak_swing_flexion_deg"
                 and o.bodySite.coding[0].code == "82169009"]
    assert len(peak_left) == 3
    assert all(o.valueQuantity.system == "http://unitsofmeasure.org" and o.valueQuantity.code == "deg"
               for o in peak_left)
    assert [round(float(o.valueQuantity.value), 1) for o in peak_left] == [
        pytest.approx((15 * 41 + 14 * 39) / 29, abs=0.1), pytest.approx(45.0, abs=0.2),
        pytest.approx(50.0, abs=0.2)]
    right = [o for o in obs if o.bodySite.coding[0].code == "6757004"]
    assert right and all(o.bodySite.coding[0].system == "http://snomed.info/sct" for o in right)


def test_fhir_names_the_patient_by_the_clinic_identifier(settings: Settings) -> None:
    system = "https://hospital.example/fhir/sid/mrn"
    with open_api(settings.model_copy(update={"fhir_identifier_system": system})) as api:
        clin, p = _seeded(api, external_id="MRN-0042", display_name="J. Doe")
        r = api.client.get(f"/v1/patients/{p['id']}/fhir", params={"metric": "rom_deg"}, headers=bearer(clin))
        assert r.status_code == 200, r.text
        clin2, other = _seeded(api)  # no external_id
        r_other = api.client.get(f"/v1/patients/{other['id']}/fhir", headers=bearer(clin2))
        assert r_other.status_code == 200, r_other.text
    bundle = Bundle.model_validate(r.json())  # R4 structure and cardinalities, references included
    by_type: dict[str, list] = {}
    for e in bundle.entry:
        by_type.setdefault(e.resource.get_resource_type(), []).append(e)
    (pat_entry,), (dev_entry,) = by_type["Patient"], by_type["Device"]
    patient = pat_entry.resource
    mrn = [i for i in patient.identifier if i.system == system]
    assert len(mrn) == 1 and mrn[0].value == "MRN-0042" and mrn[0].type.coding[0].code == "MR"
    assert any(i.value == p["id"] and i.system == "urn:gaitmon:patient-id" for i in patient.identifier)
    observations = [e.resource for e in by_type["Observation"]]
    assert len(observations) == 3 * 2
    for o in observations:
        assert o.subject.identifier.system == system and o.subject.identifier.value == "MRN-0042"
        assert o.subject.reference == pat_entry.fullUrl  # resolvable inside the Bundle
        assert o.device.reference == dev_entry.fullUrl
        assert o.effectivePeriod.start < o.effectivePeriod.end
        assert o.code.coding[0].system == "urn:gaitmon:codesystem:gait-metric"
    assert dev_entry.resource.patient.reference == pat_entry.fullUrl
    assert dev_entry.resource.version and dev_entry.resource.version[0].value
    # Without an external_id the patient is still named (by gaitmon's id) and the bundle stays valid.
    other_bundle = Bundle.model_validate(r_other.json())
    other_obs = [e.resource for e in other_bundle.entry if e.resource.get_resource_type() == "Observation"]
    assert other_obs and all(o.subject.identifier is None and o.subject.reference for o in other_obs)


def test_symmetry_completeness_and_attention_endpoints(api: Api) -> None:
    clin, p = _seeded(api)
    sym = api.client.get(f"/v1/patients/{p['id']}/symmetry", params={"bucket": "day"}, headers=bearer(clin))
    assert sym.status_code == 200
    first = sym.json()["buckets"][0]
    assert first["other"]["mean"] == 60.0 and first["symmetry_index_pct"] < 0
    comp = api.client.get(f"/v1/patients/{p['id']}/completeness", params={"days": 7}, headers=bearer(clin))
    assert comp.status_code == 200 and len(comp.json()["per_day"]) == 7
    att = api.client.get("/v1/attention", params={"limit": 10}, headers=bearer(clin))
    assert att.status_code == 200
    # The data are weeks old: the patient is silent.
    (item,) = att.json()["items"]
    assert item["patient"]["id"] == p["id"] and "silent" in [f["kind"] for f in item["flags"]]
    assert api.client.get("/v1/attention", params={"cursor": "x"}, headers=bearer(clin)).status_code == 400
