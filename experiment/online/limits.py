"""Bounded in-memory state of the server: request rate limits and the token cache.

Both are TTL caches (``cachetools``) with an injected clock, so tests step time instead of
sleeping, and both forget idle keys: a key's entry expires once all its hits are older than
the window, and at most ``max_keys`` keys are held (the least recently touched go first). No
IP address or token is written anywhere: keys are tokens' hashes or, for ``/join``, client
addresses held in memory only.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

from cachetools import TTLCache

__all__ = ["RateLimiter", "TokenCache"]

Clock = Callable[[], float]
V = TypeVar("V")


class RateLimiter:
    """At most ``limit`` hits per key in any ``window_s`` seconds (a sliding window)."""

    def __init__(
        self, *, limit: int, window_s: float, max_keys: int = 100_000, clock: Clock = time.monotonic
    ):
        self.limit = limit
        self.window_s = window_s
        self._clock = clock
        # an entry lives window_s after its last hit: then every hit in it is outside the window
        self._hits: TTLCache[str, deque[float]] = TTLCache(max_keys, window_s, timer=clock)
        self._lock = threading.Lock()

    def allow(self, key: str) -> bool:
        """Count a hit for ``key``; False (and not counted) when the key is over its limit."""
        now = self._clock()
        with self._lock:
            hits = self._hits.get(key) or deque()
            while hits and now - hits[0] >= self.window_s:
                hits.popleft()
            if len(hits) >= self.limit:
                self._hits[key] = hits
                return False
            hits.append(now)
            self._hits[key] = hits  # (re)set: the entry's lifetime restarts
            return True

    def blocked(self, key: str) -> bool:
        """Whether ``key`` is at its limit now (nothing counted)."""
        now = self._clock()
        with self._lock:
            hits = self._hits.get(key)
            return hits is not None and sum(now - t < self.window_s for t in hits) >= self.limit

    def __len__(self) -> int:
        with self._lock:
            self._hits.expire()
            return len(self._hits)


class TokenCache(Generic[V]):
    """token digest -> a value (the participant row) for ``ttl_s`` seconds, so other worker
    processes see a rotated token stop working within that time."""

    def __init__(self, *, ttl_s: float, max_keys: int = 100_000, clock: Clock = time.monotonic):
        self._cache: TTLCache[str, V] = TTLCache(max_keys, ttl_s, timer=clock)
        self._lock = threading.Lock()

    def get(self, key: str) -> V | None:
        with self._lock:
            return self._cache.get(key)

    def put(self, key: str, value: V) -> None:
        with self._lock:
            self._cache[key] = value

    def drop(self, keep: Callable[[V], bool]) -> None:
        """Forget every entry whose value ``keep`` rejects."""
        with self._lock:
            for key in [k for k, v in self._cache.items() if not keep(v)]:
                del self._cache[key]
