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
from math import floor

from fastapi import FastAPI
from limits import RateLimitItem, WindowStats, parse_many
from limits.aio.strategies import SlidingWindowCounterRateLimiter
from limits.storage import storage_from_string
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


class MemoryWindows:
    """limits' sliding window counter in memory (``SlidingWindowCounterRateLimiter`` on ``memory://``), the same
    arithmetic on a plain dict: a counter per fixed window, the previous window's count weighted by the share of
    it still inside the sliding window.

    Used from the event loop only, it needs none of what made limits' own cost ~10 % of an upload's CPU: the async
    API's 6-8 awaits per request, and in either API a lock per key, wrappers around every storage call and an
    expiry thread started anew every 10 ms under traffic. Dead counters are dropped by a sweep every
    :attr:`SWEEP_EVERY_S`.
    """

    SWEEP_EVERY_S = 10.0

    def __init__(self) -> None:
        self._counters: dict[str, list[float]] = {}  # window key -> [count, time it dies]
        self._next_sweep = 0.0

    def _count(self, key: str, now: float) -> int:
        counter = self._counters.get(key)
        if counter is None:
            return 0
        if counter[1] <= now:
            del self._counters[key]
            return 0
        return int(counter[0])

    def _window(self, item: RateLimitItem, ids: tuple[str, ...], now: float) -> tuple[str, int, float, int, float]:
        """The current window's key, the previous window's count and seconds left, the current's count and
        seconds left (limits' ``MemoryStorage.get_sliding_window``)."""
        expiry = item.get_expiry()
        key = item.key_for(*ids)
        previous = self._count(f"{key}/{int((now - expiry) / expiry)}", now)
        current_key = f"{key}/{int(now / expiry)}"
        current = self._count(current_key, now)
        previous_ttl = 0.0 if previous == 0 else (1 - (((now - expiry) / expiry) % 1)) * expiry
        current_ttl = (1 - ((now / expiry) % 1)) * expiry + expiry
        return current_key, previous, previous_ttl, current, current_ttl

    def hit(self, item: RateLimitItem, *ids: str) -> bool:
        """Count one request if the limit has room; False (nothing counted) when it has none."""
        now = time.time()
        current_key, previous, previous_ttl, current, _ = self._window(item, ids, now)
        expiry = item.get_expiry()
        if floor(previous * previous_ttl / expiry + current) + 1 > item.amount:
            return False
        counter = self._counters.get(current_key)
        if counter is None:
            self._counters[current_key] = [1, now + 2 * expiry]  # limits keeps a window twice its length
        else:
            counter[0] += 1
        if now >= self._next_sweep:
            self._next_sweep = now + self.SWEEP_EVERY_S
            for key in [k for k, (_, dies) in self._counters.items() if dies <= now]:
                del self._counters[key]
        return True

    def test(self, item: RateLimitItem, *ids: str) -> bool:
        """Whether one more request would be allowed (counts nothing)."""
        _, previous, previous_ttl, current, _ = self._window(item, ids, time.time())
        return previous * previous_ttl / item.get_expiry() + current < item.amount

    def get_window_stats(self, item: RateLimitItem, *ids: str) -> WindowStats:
        """When the limit frees its next slot, and how many it has left (limits' ``get_window_stats``)."""
        now = time.time()
        _, previous, previous_ttl, current, current_ttl = self._window(item, ids, now)
        expiry = item.get_expiry()
        remaining = max(0, item.amount - floor(previous * previous_ttl / expiry + current))
        if not (previous or current):
            return WindowStats(now, remaining)
        previous_reset = previous_ttl % (expiry / previous) if previous else math.inf
        current_reset = current_ttl % expiry if current else math.inf
        return WindowStats(now + min(previous_reset, current_reset), remaining)

    def __len__(self) -> int:
        return len(self._counters)


class RateLimitMiddleware:
    """Per-token, per-IP and failed-auth-per-IP limits: 429 problem+json with ``Retry-After`` when exceeded."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.per_token = parse_limits(settings.rate_limit_per_token)
        self.per_ip = parse_limits(settings.rate_limit_per_ip)
        self.auth_failures = parse_limits(settings.rate_limit_auth_failures_per_ip)
        # A sliding window counter: two counters per key (O(1) memory, cheap per request); a moving window would
        # keep one timestamp per request (3000 per token) and costs a thread hop per expiry sweep in memory://.
        # In memory the counters are a dict next to the event loop (MemoryWindows, no await); a shared storage
        # (redis://) is a network round trip: there limits' async API, so the loop never blocks on it.
        uri = settings.rate_limit_storage
        in_memory = uri.startswith("memory://")
        self.limiter = MemoryWindows() if in_memory else None
        self.async_limiter = (None if in_memory
                              else SlidingWindowCounterRateLimiter(storage_from_string(async_storage_uri(uri))))
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
