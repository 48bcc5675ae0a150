"""The metadata of every table, for Alembic and the schema check: imports each domain's models (add new ones here)."""

from __future__ import annotations

from sqlalchemy import MetaData

from server.auth import models as _auth_models  # noqa: F401 - each import registers its tables
from server.calibrations import models as _calibration_models  # noqa: F401
from server.db import Base
from server.patients import models as _patient_models  # noqa: F401
from server.results import models as _result_models  # noqa: F401
from server.sessions import models as _session_models  # noqa: F401
from server.trends import models as _trend_models  # noqa: F401


def all_metadata() -> MetaData:
    """The metadata with every model module imported."""
    return Base.metadata
