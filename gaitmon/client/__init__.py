"""A small Python client of the gaitmon API (httpx; sync :class:`Client` and asyncio :class:`AsyncClient`).

    from gaitmon.client import Client

    with Client("http://127.0.0.1:8000", token) as c:
        sess = c.create_session(patient_id, "visit-1", started_at, sensors)
        c.upload_batches(sess.id, batches)          # gzip'd, retried, idempotent per (sensor_id, seq)
        c.complete_session(sess.id)
        done = c.wait_for_processing(sess.id, timeout_s=120)
        df = c.get_strides(sess.id).to_dataframe()  # pandas, when installed

Error answers raise :class:`ApiError` (the server's problem details). Both clients build their requests and
parse their answers in one place (:mod:`gaitmon.client._core`).
"""

from __future__ import annotations

import importlib.metadata

try:
    __version__ = importlib.metadata.version("gaitmon")
except importlib.metadata.PackageNotFoundError:
    __version__ = "0"

from gaitmon.client._core import NO_RETRY, RetryPolicy  # noqa: E402
from gaitmon.client.async_ import AsyncClient  # noqa: E402
from gaitmon.client.errors import ApiError, FieldError  # noqa: E402
from gaitmon.client.models import (  # noqa: E402
    BatchResult,
    ClinicianCreated,
    DeviceToken,
    Me,
    Patient,
    Received,
    Sensor,
    Session,
    Stride,
    Strides,
    TrendBucket,
    Trends,
)
from gaitmon.client.sync import Client  # noqa: E402

__all__ = [
    "NO_RETRY", "ApiError", "AsyncClient", "BatchResult", "Client", "ClinicianCreated", "DeviceToken", "FieldError",
    "Me", "Patient", "Received", "RetryPolicy", "Sensor", "Session", "Stride", "Strides", "TrendBucket", "Trends",
]
