"""A small per-process cache whose entries expire after a fixed time: cachetools' TTLCache behind a lock (the
request threads of one process share it; cachetools' caches are not thread-safe on their own)."""

from __future__ import annotations

import threading
from typing import Generic, TypeVar

from cachetools import TTLCache

K = TypeVar("K")
V = TypeVar("V")


class TtlCache(Generic[K, V]):
    """Maps keys to values for ``ttl_s`` seconds; at most ``max_entries`` (the least recently used go first)."""

    def __init__(self, ttl_s: float, max_entries: int = 10_000) -> None:
        self.ttl_s = ttl_s
        self._data: TTLCache[K, V] = TTLCache(maxsize=max_entries, ttl=ttl_s)
        self._lock = threading.Lock()

    def get(self, key: K) -> V | None:
        """The value stored under ``key`` if it has not expired, else None."""
        with self._lock:
            return self._data.get(key)

    def put(self, key: K, value: V) -> None:
        """Store ``value`` under ``key`` for ``ttl_s`` seconds."""
        with self._lock:
            self._data[key] = value

    def discard(self, key: K) -> None:
        """Forget ``key``."""
        with self._lock:
            self._data.pop(key, None)
