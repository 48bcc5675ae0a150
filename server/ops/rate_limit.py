"""Per-token and per-client-address rate limits (the ``limits`` library), and slowing down guessed tokens.

Every ``/v1`` request counts against its client address (``GAITMON_RATE_LIMIT_PER_IP``) and, when it carries an
``Authorization`` header, against that token (``GAITMON_RATE_LIMIT_PER_TOKEN``; the key is a hash of the header,
never the token). A limit that is exceeded answers 429 problem+json with ``Retry-After`` in seconds.

Each 401 counts against ``GAITMON_RATE_LIMIT_AUTH_FAILURES_PER_IP``; once that budget is spent the address gets
429 for every token it has not been seen to use successfully, so guessing is slowed to the budget while the
working phones behind the same clinic NAT keep uploading.

The counters live in ``GAITMON_RATE_LIMIT_STORAGE``: ``memory://`` counts per process (limits per API process),
a shared storage such as ``redis://host:6379`` (needs the ``redis`` package) counts for all of them.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from collections import OrderedDict

from fastapi import FastAPI
from limits import RateLimitItem, parse_many
from limits.aio.strategies import SlidingWindowCounterRateLimiter as AsyncSlidingWindowCounterRateLimiter
from limits.storage import storage_from_string
from limits.strategies import SlidingWindowCounterRateLimiter
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.config import Settings
from server.errors import PROBLEM_JSON, problem_body

log = logging.getLogger("gaitmon.api")

LIMITED_PREFIX = "/v1"
# Tokens seen to authenticate, per address; bounded so a flood of distinct tokens cannot grow memory.
KNOWN_GOOD_MAX = 10_000


def parse_limits(spec: str) -> list[RateLimitItem]:
    """``"3000/minute;100/second"`` -> limit items; an empty string means no limit."""
    return parse_many(spec) if spec.strip() else []


def async_storage_uri(uri: str) -> str:
    """The ``limits`` storage URI of its async API (``memory://`` -> ``async+memory://``)."""
    return uri if uri.startswith("async+") else f"async+{uri}"


class RateLimitMiddleware:
    """Per-token, per-IP and failed-auth-per-IP limits: 429 problem+json with ``Retry-After`` when exceeded."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.per_token = parse_limits(settings.rate_limit_per_token)
        self.per_ip = parse_limits(settings.rate_limit_per_ip)
        self.auth_failures = parse_limits(settings.rate_limit_auth_failures_per_ip)
        # A sliding window counter: two counters per key (O(1) memory, cheap per request); a moving window would
        # keep one timestamp per request (3000 per token) and costs a thread hop per expiry sweep in memory://.
        # In memory the counters are a dict next to the event loop: the synchronous API reads and counts without
        # an await (the async one awaits 6-8 times per request, ~10 % of an upload's CPU). A shared storage
        # (redis://) is a network round trip: there the async API, so the loop never blocks on it.
        uri = settings.rate_limit_storage
        in_memory = uri.startswith("memory://")
        self.limiter = SlidingWindowCounterRateLimiter(storage_from_string(uri)) if in_memory else None
        self.async_limiter = (None if in_memory
                              else AsyncSlidingWindowCounterRateLimiter(storage_from_string(async_storage_uri(uri))))
        self._known_good: OrderedDict[tuple[str, str], None] = OrderedDict()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope["path"].startswith(LIMITED_PREFIX) or scope["method"] == "OPTIONS":
            await self.app(scope, receive, send)
            return
        ip = (scope.get("client") or ("unknown", 0))[0]
        auth = next((v for k, v in scope.get("headers", []) if k == b"authorization"), None)
        token_key = hashlib.sha256(auth).hexdigest()[:32] if auth else None

        if token_key is None or (ip, token_key) not in self._known_good:
            retry = await self._exhausted(self.auth_failures, "authfail", ip)
            if retry is not None:
                log.warning("client %s: too many failed authentications; 429 for %d s", ip, retry)
                await self._reject(scope, receive, send, retry, "Too many failed authentications from this address")
                return
        retry = await self._hit(self.per_ip, "ip", ip)
        if retry is None and token_key is not None:
            retry = await self._hit(self.per_token, "token", token_key)
        if retry is not None:
            await self._reject(scope, receive, send, retry, "Too many requests")
            return

        status = 0

        async def send_and_watch(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        await self.app(scope, receive, send_and_watch)
        if status == 401:
            await self._count(self.auth_failures, "authfail", ip)
            if token_key is not None:
                self._known_good.pop((ip, token_key), None)
        elif token_key is not None and status:
            self._remember(ip, token_key)

    def _remember(self, ip: str, token_key: str) -> None:
        key = (ip, token_key)
        self._known_good[key] = None
        self._known_good.move_to_end(key)
        while len(self._known_good) > KNOWN_GOOD_MAX:
            self._known_good.popitem(last=False)

    async def _exhausted(self, items: list[RateLimitItem], *ids: str) -> int | None:
        """Seconds until the first exhausted limit frees a slot, or None when all have room (counts nothing)."""
        for item in items:
            if self.limiter is not None:
                if not self.limiter.test(item, *ids):
                    return _seconds_until(self.limiter.get_window_stats(item, *ids).reset_time)
            elif not await self.async_limiter.test(item, *ids):
                return _seconds_until((await self.async_limiter.get_window_stats(item, *ids)).reset_time)
        return None

    async def _hit(self, items: list[RateLimitItem], *ids: str) -> int | None:
        """Count one request against every limit; seconds to wait when one is exceeded, else None."""
        for item in items:
            if self.limiter is not None:
                if not self.limiter.hit(item, *ids):
                    return _seconds_until(self.limiter.get_window_stats(item, *ids).reset_time)
            elif not await self.async_limiter.hit(item, *ids):
                return _seconds_until((await self.async_limiter.get_window_stats(item, *ids)).reset_time)
        return None

    async def _count(self, items: list[RateLimitItem], *ids: str) -> None:
        """Count one event against every limit, whether or not it is exceeded."""
        for item in items:
            if self.limiter is not None:
                self.limiter.hit(item, *ids)
            else:
                await self.async_limiter.hit(item, *ids)

    @staticmethod
    async def _reject(scope: Scope, receive: Receive, send: Send, retry_after: int, detail: str) -> None:
        body = problem_body(429, f"{detail}; retry after {retry_after} s", slug="rate-limited",
                            instance=scope.get("path"))
        resp = JSONResponse(body, status_code=429, media_type=PROBLEM_JSON,
                            headers={"Retry-After": str(retry_after)})
        await resp(scope, receive, send)


def _seconds_until(reset_time: float) -> int:
    """Retry-After: whole seconds until a slot frees, at least 1."""
    return max(1, math.ceil(reset_time - time.time()))


def install(app: FastAPI, settings: Settings) -> None:
    """Add the rate-limit middleware when any limit is configured."""
    if settings.rate_limit_per_token or settings.rate_limit_per_ip or settings.rate_limit_auth_failures_per_ip:
        app.add_middleware(RateLimitMiddleware, settings=settings)
