"""Property-based requests generated from the served OpenAPI document (schemathesis): no operation answers 5xx,
whatever the path ids, query values and bodies. Bounded: a few examples per operation, on SQLite."""

from __future__ import annotations

import tempfile
from pathlib import Path

import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from server.app import create_app
from server.auth.service import issue_token
from server.config import Settings
from server.migrate import upgrade_to_head

MAX_EXAMPLES = 5

# The schema is read at collection time, so the app (on a migrated SQLite file of its own) is made here.
_TMP = Path(tempfile.mkdtemp(prefix="gaitmon-schemathesis-"))
_URL = f"sqlite:///{_TMP / 'gaitmon.sqlite'}"
upgrade_to_head(_URL)
APP = create_app(Settings(database_url=_URL, data_dir=_TMP / "data", job_runner="manual"))
with APP.state.sessionmaker() as _db:
    _, ADMIN = issue_token(_db, role="admin", name="schemathesis")
    _db.commit()

schema = schemathesis.openapi.from_asgi("/openapi.json", APP)


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_operation_answers_a_server_error(case) -> None:  # noqa: ANN001
    response = case.call(headers={"Authorization": f"Bearer {ADMIN}"})
    case.validate_response(response, checks=[not_a_server_error])
