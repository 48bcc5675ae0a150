"""Every route declares what it answers: a response model for JSON, a response class for the rest."""

from __future__ import annotations

from server.app import create_app
from server.config import Settings


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
