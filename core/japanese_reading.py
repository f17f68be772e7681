"""How Japanese text is pronounced, for scoring typed answers: the OpenJTalk front end's
reading in katakana (kanji, hiragana and katakana spellings of a word read alike; long vowels
as ``ー``: おかあさん, おかーさん and お母さん are all オカーサン, せんせい and 先生 センセー),
split into morae."""

from __future__ import annotations

import contextlib
import functools
import io
import re
import unicodedata

from facelab.errors import SpeechError

__all__ = ["first_unsaid_keyword", "morae", "pronunciation"]

_SMALL = set("ャュョァィゥェォヮ")
#: an e-row mora and イ: the dictionary reads kanji as a long vowel (先生 センセー) and kana as
#: written (せんせい センセイ); both are read long
_E_I = re.compile("([エケセテネヘメレゲゼデベペェ])イ")
_DROP = re.compile(r"[\s、。，．,.!?！？「」『』（）()・…〜~\-]+")


@functools.cache
def _frontend():
    """pyopenjtalk's g2p, imported once with its import-time notices kept off the console."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            import pyopenjtalk
        except ImportError:
            raise SpeechError("pyopenjtalk-plus is not installed (pip install "
                              "'facelab[stimuli]')") from None  # fmt: skip
    return pyopenjtalk.g2p


def _katakana(text: str) -> str:
    return "".join(chr(ord(c) + 0x60) if "ぁ" <= c <= "ゖ" else c for c in text)


@functools.lru_cache(maxsize=4096)
def pronunciation(text: str) -> str:
    """The katakana pronunciation of ``text`` (NFKC-normalised; punctuation and spaces
    dropped; kana read as written, kanji by the dictionary). Parts apart by spaces are read
    apart, as the writer parted them: 朝 雨 is アサアメ, where 朝雨 would be read as one
    word."""
    parts = unicodedata.normalize("NFKC", text).split()
    return "".join(_reading(part) for part in parts)


@functools.lru_cache(maxsize=4096)
def _reading(part: str) -> str:
    plain = _DROP.sub("", part)
    if not plain:
        return ""
    kana = _DROP.sub("", _katakana(str(_frontend()(plain, kana=True))))
    return _E_I.sub(r"\1ー", kana)  # 先生 センセー, but kana せんせい comes back センセイ


def morae(kana: str) -> list[str]:
    """Katakana split into morae: a small ャュョァィゥェォ joins the mora before it; ッ, ン
    and ー are morae of their own."""
    out: list[str] = []
    for c in kana:
        if c in _SMALL and out:
            out[-1] += c
        else:
            out.append(c)
    return out


def first_unsaid_keyword(said: str, keywords: list[str]) -> str | None:
    """The first of ``keywords`` that is not said in ``said`` after the ones before it (as
    pronounced: its morae found in the sentence's, in order), or None when all are - an
    answer that repeats the sentence word for word then scores every keyword."""
    heard, at = morae(pronunciation(said)), 0
    for word in keywords:
        key = morae(pronunciation(word))
        found = next((i for i in range(at, len(heard) - len(key) + 1)
                      if heard[i : i + len(key)] == key), None)  # fmt: skip
        if not key or found is None:
            return word
        at = found + len(key)
    return None
