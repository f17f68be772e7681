"""The bounded memo behind OpenJTalk's, the alignments' and the noises' per-process caches:
least recently used entries go first, by count or by bytes; the newest entry always stays."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from facelab.bounded_memo import BoundedMemo


def test_the_least_recently_used_entry_goes_first() -> None:
    memo: BoundedMemo[str] = BoundedMemo(max_items=2)
    memo.put("a", "A")
    memo.put("b", "B")
    assert memo.get("a") == "A"  # used: "b" is now the oldest
    memo.put("c", "C")
    assert memo.get("b") is None and memo.get("a") == "A" and memo.get("c") == "C"
    assert len(memo) == 2 and memo.values() == ["A", "C"]


def test_a_byte_bound_counts_each_entry_once_and_keeps_the_newest() -> None:
    memo: BoundedMemo[np.ndarray] = BoundedMemo(max_bytes=100, size_of=lambda x: x.nbytes)
    memo.put("a", np.zeros(5))  # 40 bytes
    memo.put("a", np.zeros(10))  # replaced: 80, not 120
    assert len(memo) == 1 and memo.bytes == 80
    memo.put("b", np.zeros(5))  # 120 > 100: "a" goes
    assert memo.get("a") is None and memo.bytes == 40
    memo.put("big", np.zeros(50))  # larger than the bound alone: kept, everything else goes
    assert memo.values()[0].nbytes == 400 and len(memo) == 1 and memo.bytes == 400
    memo.clear()
    assert len(memo) == 0 and memo.bytes == 0 and memo.get("big") is None


def test_a_byte_bound_needs_a_size() -> None:
    with pytest.raises(ValueError, match="size_of"):
        BoundedMemo(max_bytes=10)


def test_threads_storing_at_once_keep_the_bound_and_the_byte_count() -> None:
    memo: BoundedMemo[bytes] = BoundedMemo(max_items=50, max_bytes=10_000, size_of=len)

    def work(t: int) -> None:
        for i in range(500):
            memo.put((t, i % 80), bytes(100 + i % 7))
            memo.get((t, (i * 7) % 80))

    threads = [threading.Thread(target=work, args=(t,)) for t in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(memo) <= 50 and memo.bytes == sum(len(v) for v in memo.values()) <= 10_000
