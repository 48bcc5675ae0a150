"""The per-process cache of token identities and sensor rates forgets entries after its time and beyond its size."""

from __future__ import annotations

import time

from server.ttl_cache import TtlCache


def test_entries_expire_and_the_size_is_bounded() -> None:
    cache: TtlCache[str, int] = TtlCache(ttl_s=0.05, max_entries=2)
    cache.put("a", 1)
    assert cache.get("a") == 1 and cache.get("b") is None
    time.sleep(0.08)
    assert cache.get("a") is None
    for i, key in enumerate("xyz"):
        cache.put(key, i)
    assert cache.get("x") is None and cache.get("z") == 2  # the oldest went first
    cache.discard("z")
    assert cache.get("z") is None
