"""Scoring typed answers to speech (words or sentences heard in noise) against what was said.

Both are compared as pronounced, not as spelled: a ``reader`` turns text into its katakana
pronunciation (:func:`facelab.japanese_reading.pronunciation` - kana and kanji
variants read alike, long vowels normalised), split into morae. Scores:

* ``morae_correct`` / ``mora_score`` - the target's morae the answer reproduced in order
  (their longest common subsequence) and their share of the target's;
* ``keywords_correct`` of ``keywords_total`` / ``keyword_score`` - the target's keywords (by
  default its words as given, e.g. ``猫 走る``) found in the answer's pronunciation, in the
  order said, each in its own part of the answer (the most keywords so placed): a keyword
  heard inside another one's reading does not count twice (箱 ハコ is in 運んだ ハコンダ:
  "大きな 運んだ" is 2 of 大きな 箱 運んだ, not 3); with ``tolerant`` a keyword of three or
  more morae also counts with one mora wrong (a typo);
* ``exact`` - the whole pronunciation equal (extra words make it 0; the mora score is not
  lowered by them, the usual convention of open-set scoring).

Pure: the reader is passed in.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import pandas as pd

__all__ = ["TypedScore", "score_table", "score_typed"]

Reader = Callable[[str], str]
Splitter = Callable[[str], list[str]]


@dataclass(frozen=True)
class TypedScore:
    target_reading: str
    response_reading: str
    morae: int
    morae_correct: int
    mora_score: float
    keywords_total: int
    keywords_correct: int
    keyword_score: float
    exact: int


def _lcs(a: Sequence[str], b: Sequence[str]) -> int:
    row = [0] * (len(b) + 1)
    for x in a:
        prev = 0
        for j, y in enumerate(b, 1):
            prev, row[j] = row[j], prev + 1 if x == y else max(row[j], row[j - 1])
    return row[-1]


def _matches(window: Sequence[str], needle: Sequence[str], *, tolerant: bool) -> bool:
    allowed = 1 if tolerant and len(needle) >= 3 else 0
    return sum(a != b for a, b in zip(window, needle, strict=True)) <= allowed


def _keywords_found(hay: list[str], keys: list[list[str]], *, tolerant: bool) -> int:
    """The most keywords found in ``hay`` in order, each on morae of its own (dynamic
    programming over keywords x answer morae)."""
    m = len(hay)
    best = [0] * (m + 1)  # best[j]: keywords placed so far within hay[:j]
    for key in keys:
        k = len(key)
        nxt = best[:]
        for j in range(1, m + 1):
            nxt[j] = max(nxt[j], nxt[j - 1])
            if k and j >= k and _matches(hay[j - k : j], key, tolerant=tolerant):
                nxt[j] = max(nxt[j], best[j - k] + 1)
        best = nxt
    return best[m] + sum(1 for key in keys if not key)


def score_typed(
    target: str, response: str, *, reader: Reader, split: Splitter,
    keywords: Sequence[str] | None = None, tolerant: bool = True,
) -> TypedScore:  # fmt: skip
    """Score one typed ``response`` against ``target`` (see the module)."""
    want, got = reader(target), reader(response)
    want_m, got_m = split(want), split(got)
    words = list(keywords) if keywords is not None else (target.split() or [target])
    keys = [split(reader(w)) for w in words if reader(w)]
    found = _keywords_found(got_m, keys, tolerant=tolerant)
    hit = _lcs(want_m, got_m)
    return TypedScore(
        target_reading=want, response_reading=got, morae=len(want_m), morae_correct=hit,
        mora_score=hit / len(want_m) if want_m else float("nan"), keywords_total=len(keys),
        keywords_correct=found, keyword_score=found / len(keys) if keys else float("nan"),
        exact=int(bool(want) and want == got),
    )  # fmt: skip


def score_table(
    pairs: pd.DataFrame, *, reader: Reader, split: Splitter, tolerant: bool = True
) -> pd.DataFrame:
    """``pairs`` (``target, response`` and optionally ``keywords``, space-separated) with the
    :class:`TypedScore` columns added."""
    rows = []
    for r in pairs.to_dict("records"):
        kw = r.get("keywords")
        keys = str(kw).split() if isinstance(kw, str) and kw.strip() else None
        said = "" if pd.isna(r["response"]) else str(r["response"])
        score = score_typed(str(r["target"]), said, reader=reader, split=split, keywords=keys,
                            tolerant=tolerant)  # fmt: skip
        rows.append({**r, **asdict(score)})
    return pd.DataFrame(rows)
