"""The blocking client (``httpx.Client``); safe to share between threads."""

from __future__ import annotations

import random
import time
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime
from typing import Any, TypeVar

import httpx

from gaitmon.client import _core
from gaitmon.client import models as m
from gaitmon.client._core import Call, RetryPolicy

T = TypeVar("T")


class Client:
    """gaitmon API client.

    ``Client("http://127.0.0.1:8000", token)`` — every call retries as :class:`RetryPolicy` says, raises
    :class:`~gaitmon.client.ApiError` for an error answer, and returns the typed response.
    """

    def __init__(self, base_url: str, token: str | None = None, *, timeout_s: float = 30.0,
                 retry: RetryPolicy | None = None, gzip: bool = True, headers: Mapping[str, str] | None = None,
                 transport: httpx.BaseTransport | None = None, seed: int | None = None) -> None:
        self.retry = retry or RetryPolicy()
        self.gzip = gzip
        self._rng = random.Random(seed)
        self._http = httpx.Client(base_url=base_url.rstrip("/"), headers=_core.base_headers(token, headers),
                                  timeout=timeout_s, transport=transport)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def send(self, call: Call[T]) -> T:
        """Send one call with retries; the parsed result, or ApiError / the last transport error."""
        kw = call.request_kwargs()
        attempt = 0
        while True:
            attempt += 1
            try:
                resp = self._http.request(call.method, call.path, **kw)
            except httpx.TransportError as exc:
                delay = _core.delay_after_error(call, exc, attempt, self.retry, self._rng)
                if delay is None:
                    raise
            else:
                delay = _core.delay_after_response(call, resp, attempt, self.retry, self._rng)
                if delay is None:
                    return _core.result(call, resp)
            time.sleep(delay)

    # --- operations (see gaitmon.client._core for the requests) ---------------------------------------------

    def me(self) -> m.Me:
        return self.send(_core.me())

    def create_clinician(self, name: str, email: str | None = None) -> m.ClinicianCreated:
        return self.send(_core.create_clinician(name, email))

    def create_patient(self, *, display_name: str | None = None, external_id: str | None = None,
                       affected_leg: str | None = None, timezone: str | None = None,
                       clinician_id: str | None = None) -> m.Patient:
        return self.send(_core.create_patient(
            {"display_name": display_name, "external_id": external_id, "affected_leg": affected_leg,
             "timezone": timezone, "clinician_id": clinician_id}))

    def get_patient(self, patient_id: str) -> m.Patient:
        return self.send(_core.get_patient(patient_id))

    def create_device_token(self, patient_id: str, name: str | None = None) -> m.DeviceToken:
        return self.send(_core.create_device_token(patient_id, name))

    def create_session(self, patient_id: str, client_session_id: str, started_at: datetime | str,
                       sensors: Sequence[Mapping[str, Any] | m.Sensor], activity: str = "walking") -> m.Session:
        """Start a session; the same ``client_session_id`` again returns the same session (safe to resend)."""
        return self.send(_core.create_session(
            _core.session_body(patient_id, client_session_id, started_at, sensors, activity)))

    def get_session(self, session_id: str) -> m.Session:
        return self.send(_core.get_session(session_id))

    def upload_batch(self, session_id: str, batch: Mapping[str, Any], *, gzip: bool | None = None) -> m.BatchResult:
        """Upload one batch ``{sensor_id, seq, t0_ms, gyro, acc[, timestamps_ms]}`` (numpy arrays accepted).

        Resending the same ``(sensor_id, seq)`` with the same samples is acknowledged (``duplicate=True``).
        """
        return self.send(_core.upload_batch(session_id, batch, self.gzip if gzip is None else gzip))

    def upload_batches(self, session_id: str, batches: Iterable[Mapping[str, Any]], *,
                       concurrency: int = 1) -> list[m.BatchResult]:
        """Upload many batches (``concurrency`` at a time, results in input order)."""
        if concurrency <= 1:
            return [self.upload_batch(session_id, b) for b in batches]
        with ThreadPoolExecutor(max_workers=concurrency) as pool:
            return list(pool.map(lambda b: self.upload_batch(session_id, b), batches))

    def complete_session(self, session_id: str) -> m.Session:
        return self.send(_core.complete_session(session_id))

    def wait_for_processing(self, session_id: str, timeout_s: float = 300.0, poll_s: float = 1.0) -> m.Session:
        """Poll until the session is ``done`` or ``failed`` and return it; TimeoutError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            sess = self.get_session(session_id)
            if sess.finished:
                return sess
            if time.monotonic() >= deadline:
                raise TimeoutError(f"session {session_id} still {sess.status} after {timeout_s:g} s")
            time.sleep(min(poll_s, max(0.0, deadline - time.monotonic())))

    def get_strides(self, session_id: str, leg: str | None = None) -> m.Strides:
        return self.send(_core.get_strides(session_id, leg))

    def get_trends(self, patient_id: str, metric: str = "peak_swing_flexion_deg", *, leg: str | None = None,
                   bucket: str = "day", start: str | None = None, end: str | None = None) -> m.Trends:
        return self.send(_core.get_trends(patient_id, metric=metric, leg=leg, bucket=bucket, start=start, end=end))
