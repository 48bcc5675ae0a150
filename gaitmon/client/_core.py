"""What the sync and the async client share: the requests (built once), the retry decisions, response parsing.

Each API operation is a :class:`Call`: method, path, body, the statuses that mean success, whether it is safe to
send again, and how to parse the answer. :class:`~gaitmon.client.Client` and :class:`~gaitmon.client.AsyncClient`
only send calls and sleep between attempts.
"""

from __future__ import annotations

import gzip as gzip_lib
import json
import random
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from email.utils import parsedate_to_datetime
from typing import Any, Generic, TypeVar

import httpx

from gaitmon.client import models as m
from gaitmon.client.errors import ApiError

T = TypeVar("T")

RETRY_STATUSES_ALWAYS = frozenset({429, 503})  # the server said "not now": nothing was done
RETRY_STATUSES_IDEMPOTENT = frozenset({502, 504})  # a proxy's answer: the request may or may not have run


@dataclass(frozen=True)
class RetryPolicy:
    """Exponential back-off with full jitter; a server's ``Retry-After`` is honoured (up to ``max_retry_after_s``).

    Connection failures (the request never reached the server) and 429/503 are retried for every call;
    read timeouts, dropped connections and 502/504 only for calls the API makes idempotent (all but creating a
    patient, a clinician or a device token).
    """

    max_attempts: int = 6
    base_delay_s: float = 0.5
    max_delay_s: float = 20.0
    max_retry_after_s: float = 120.0

    def backoff_s(self, attempt: int, rng: random.Random) -> float:
        """Delay before attempt ``attempt + 1`` (``attempt`` counts from 1): uniform in (0, base * 2^(attempt-1)]."""
        cap = min(self.max_delay_s, self.base_delay_s * 2 ** (attempt - 1))
        return rng.uniform(0.1 * cap, cap)


NO_RETRY = RetryPolicy(max_attempts=1)


@dataclass(frozen=True)
class Call(Generic[T]):
    method: str
    path: str
    parse: Callable[[httpx.Response], T]
    ok: tuple[int, ...] = (200,)
    idempotent: bool = True
    json_body: Any = None
    gzip: bool = False
    params: Mapping[str, Any] | None = None
    headers: Mapping[str, str] = field(default_factory=dict)

    def request_kwargs(self) -> dict[str, Any]:
        kw: dict[str, Any] = {"params": {k: v for k, v in (self.params or {}).items() if v is not None}}
        headers = dict(self.headers)
        if self.json_body is not None:
            data = json.dumps(self.json_body, separators=(",", ":"), allow_nan=False).encode()
            headers["Content-Type"] = "application/json"
            if self.gzip:
                data = gzip_lib.compress(data, compresslevel=6)
                headers["Content-Encoding"] = "gzip"
            kw["content"] = data
        kw["headers"] = headers
        return kw


def retry_after_s(resp: httpx.Response) -> float | None:
    """``Retry-After`` in seconds (delta-seconds or an HTTP date), None when absent or unreadable."""
    value = resp.headers.get("retry-after")
    if not value:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


def delay_after_response(call: Call[Any], resp: httpx.Response, attempt: int, policy: RetryPolicy,
                         rng: random.Random) -> float | None:
    """Seconds to wait before sending ``call`` again after ``resp``, or None to stop (success or final error)."""
    if resp.status_code in call.ok or attempt >= policy.max_attempts:
        return None
    if resp.status_code in RETRY_STATUSES_ALWAYS or (call.idempotent and resp.status_code in RETRY_STATUSES_IDEMPOTENT):
        server = retry_after_s(resp)
        if server is None:
            return policy.backoff_s(attempt, rng)
        if server > policy.max_retry_after_s:
            return None
        # A little jitter on top, so clients told the same instant do not come back together.
        return server + rng.uniform(0.0, min(1.0, 0.1 * server + 0.1))
    return None


def delay_after_error(call: Call[Any], exc: httpx.TransportError, attempt: int, policy: RetryPolicy,
                      rng: random.Random) -> float | None:
    """Seconds to wait after a transport error, or None to re-raise it."""
    if attempt >= policy.max_attempts:
        return None
    never_sent = isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout)
    if never_sent or call.idempotent:
        return policy.backoff_s(attempt, rng)
    return None


def result(call: Call[T], resp: httpx.Response) -> T:
    """The parsed success, or :class:`ApiError`."""
    if resp.status_code not in call.ok:
        raise ApiError.from_response(resp, retry_after_s=retry_after_s(resp))
    return call.parse(resp)


def _model(cls: type[m.ApiModel]) -> Callable[[httpx.Response], Any]:
    return lambda resp: cls.model_validate(resp.json())


def _plain(value: Any) -> Any:  # noqa: ANN401 - JSON values
    """numpy arrays and scalars as JSON lists and numbers; datetimes as ISO 8601."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, datetime):
        if value.tzinfo is None:
            raise ValueError("started_at needs a time zone (e.g. datetime.now(UTC))")
        return value.isoformat()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


# --- the calls -------------------------------------------------------------------------------------------------


def me() -> Call[m.Me]:
    return Call("GET", "/v1/me", _model(m.Me))


def create_clinician(name: str, email: str | None) -> Call[m.ClinicianCreated]:
    return Call("POST", "/v1/clinicians", _model(m.ClinicianCreated), ok=(201,), idempotent=False,
                json_body={"name": name, "email": email})


def create_patient(body: Mapping[str, Any]) -> Call[m.Patient]:
    return Call("POST", "/v1/patients", _model(m.Patient), ok=(201,), idempotent=False,
                json_body={k: v for k, v in body.items() if v is not None})


def get_patient(patient_id: str) -> Call[m.Patient]:
    return Call("GET", f"/v1/patients/{patient_id}", _model(m.Patient))


def create_device_token(patient_id: str, name: str | None) -> Call[m.DeviceToken]:
    return Call("POST", f"/v1/patients/{patient_id}/device-tokens", _model(m.DeviceToken), ok=(201,),
                idempotent=False, json_body={"name": name} if name else {})


def create_session(body: Mapping[str, Any]) -> Call[m.Session]:
    # 201 created, 200 the same client_session_id again: the same session either way.
    return Call("POST", "/v1/sessions", _model(m.Session), ok=(200, 201), json_body=_plain(body))


def get_session(session_id: str) -> Call[m.Session]:
    return Call("GET", f"/v1/sessions/{session_id}", _model(m.Session))


def upload_batch(session_id: str, batch: Mapping[str, Any], gzip: bool) -> Call[m.BatchResult]:
    # 201 stored, 200 an identical replay (acknowledged, stored once).
    return Call("POST", f"/v1/sessions/{session_id}/batches", _model(m.BatchResult), ok=(200, 201),
                json_body=_plain(batch), gzip=gzip)


def complete_session(session_id: str) -> Call[m.Session]:
    return Call("POST", f"/v1/sessions/{session_id}/complete", _model(m.Session), ok=(200, 202))


def get_strides(session_id: str, leg: str | None) -> Call[m.Strides]:
    return Call("GET", f"/v1/sessions/{session_id}/strides", _model(m.Strides), params={"leg": leg})


def get_trends(patient_id: str, *, metric: str, leg: str | None, bucket: str, start: str | None,
               end: str | None) -> Call[m.Trends]:
    return Call("GET", f"/v1/patients/{patient_id}/trends", _model(m.Trends),
                params={"metric": metric, "leg": leg, "bucket": bucket, "from": start, "to": end})


def session_body(patient_id: str, client_session_id: str, started_at: datetime | str,
                 sensors: Sequence[Mapping[str, Any] | m.Sensor], activity: str) -> dict[str, Any]:
    return {"patient_id": patient_id, "client_session_id": client_session_id, "started_at": started_at,
            "activity": activity,
            "sensors": [s.model_dump() if isinstance(s, m.ApiModel) else dict(s) for s in sensors]}


def base_headers(token: str | None, extra: Mapping[str, str] | None) -> dict[str, str]:
    from gaitmon.client import __version__

    headers = {"User-Agent": f"gaitmon-client/{__version__}", "Accept": "application/json"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    headers.update(extra or {})
    return headers
