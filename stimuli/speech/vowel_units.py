"""The vowels of a phoneme timeline as a stimulus' ``expected_vowels`` may list them (a light
module: ``facelab validate`` reads texts with it without loading the analyser)."""

from __future__ import annotations

from collections.abc import Sequence

from facelab.stimuli.speech.audio import Phone
from facelab.stimuli.speech.track import VOWELS

__all__ = ["Unit", "vowel_readings"]

#: a vowel unit: (vowel, start s, end s) - one vowel phoneme, or a run of one vowel spoken on
Unit = tuple[str, float, float]


def vowel_readings(phones: Sequence[Phone]) -> dict[str, list[Unit]]:
    """Every way of listing the vowels of timed ``phones`` that a stimulus' ``expected_vowels``
    may give: each vowel phoneme (OpenJTalk writes a long vowel as two: あー, ええ are ``a a``,
    ``e e``) or each run of one vowel spoken on (あー is ``a``); devoiced vowels (``U``, ``I``:
    です ``d e s U``) counted or not. {vowels: their units}, the first the fullest reading."""
    out: dict[str, list[Unit]] = {}
    for merge, devoiced in ((False, True), (True, True), (False, False), (True, False)):
        units: list[Unit] = []
        joinable = False  # the last unit may be continued by the same vowel
        for p in phones:
            v = p.phoneme.lower()
            if v not in VOWELS or len(p.phoneme) != 1:
                joinable = False
                continue
            if p.phoneme.isupper() and not devoiced:
                joinable = False
                continue
            if merge and joinable and units[-1][0] == v:
                units[-1] = (v, units[-1][1], p.end)
            else:
                units.append((v, p.start, p.end))
            joinable = True
        out.setdefault("".join(u[0] for u in units), units)
    return out
