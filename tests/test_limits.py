"""The server's bounded in-memory state (experiment/online/limits.py), on a stepped clock."""

from __future__ import annotations

from facelab.experiment.online.limits import RateLimiter, TokenCache


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_rate_limit_is_a_sliding_window() -> None:
    clock = Clock()
    limiter = RateLimiter(limit=3, window_s=60.0, clock=clock)
    assert [limiter.allow("a") for _ in range(4)] == [True, True, True, False]
    assert limiter.allow("b")  # keys are independent
    clock.t += 59.9
    assert not limiter.allow("a")  # still inside the window: the refusals were not counted
    clock.t += 0.1
    assert limiter.allow("a")  # the first three hits are now 60 s old


def test_idle_keys_are_forgotten_and_memory_is_bounded() -> None:
    clock = Clock()
    limiter = RateLimiter(limit=5, window_s=4.0, max_keys=100, clock=clock)
    for i in range(1000):
        limiter.allow(f"token{i}")
    assert len(limiter) == 100  # the least recently used went first
    clock.t += 4.0
    assert len(limiter) == 0  # every hit outside the window: nothing is kept


def test_token_cache_expires_and_drops_a_participant() -> None:
    clock = Clock()
    cache: TokenCache[str] = TokenCache(ttl_s=5.0, clock=clock)
    cache.put("d1", "P0001")
    cache.put("d2", "P0002")
    assert cache.get("d1") == "P0001"
    cache.drop(lambda p: p != "P0001")
    assert cache.get("d1") is None and cache.get("d2") == "P0002"
    clock.t += 5.0
    assert cache.get("d2") is None
