"""eSpeak NG as a second Japanese voice: audio with its own phoneme timing."""

from __future__ import annotations

import numpy as np
import pytest

from facelab.errors import SpeechError
from facelab.stimuli.speech.espeak import EspeakVoice, espeak_synthesize, kana_of
from facelab.stimuli.speech.training import ESPEAK_HELDOUT, ESPEAK_TRAIN


def _level_db(samples: np.ndarray, rate: int, a: float, b: float) -> float:
    seg = samples[int(a * rate) : int(b * rate)]
    return float(10 * np.log10(np.mean(seg.astype(float) ** 2) + 1e-12))


def test_kanji_are_read_as_kana() -> None:
    assert kana_of("今日は雨です。") == "キョーワアメデス。"


def test_phones_are_timed_on_the_audio() -> None:
    speech = espeak_synthesize("あ。い。う。", voice=EspeakVoice("m3"), sample_rate=16_000)
    assert speech.sample_rate == 16_000 and speech.source.startswith("espeak:espeak_ja+m3:")
    names = [p.phoneme for p in speech.phones]
    vowels = [p for p in speech.phones if p.phoneme in "aiu"]
    assert [p.phoneme for p in vowels] == ["a", "i", "u"] and "pau" in names
    assert speech.phones[0].start == 0
    assert speech.phones[-1].end == pytest.approx(speech.duration_s, abs=1e-3)
    for prev, nxt in zip(speech.phones, speech.phones[1:], strict=False):
        assert prev.end == pytest.approx(nxt.start)
    # each vowel is loud, each pause between them is near silent
    for p in speech.phones:
        if p.end - p.start < 0.06:
            continue
        level = _level_db(speech.samples, 16_000, p.start + 0.02, p.end - 0.02)
        if p.phoneme in "aiu":
            assert level > -35, p
        elif p.phoneme == "pau" and p.end - p.start > 0.1:
            assert level < -50, p


def test_consonants_map_to_openjtalk_names() -> None:
    speech = espeak_synthesize("しゃしんをとったら、ちいさいふねがみえた。")
    names = {p.phoneme for p in speech.phones}
    assert {"sh", "ch", "ts", "f", "N", "y", "t", "r"} & names >= {"sh", "ch", "f", "N"}
    from facelab.stimuli.speech.track import phoneme_viseme

    for name in names:
        phoneme_viseme(name)  # every name is one the rest of facelab knows


def test_voices_are_distinct_and_held_out_ones_unseen() -> None:
    assert not set(ESPEAK_HELDOUT) & set(ESPEAK_TRAIN)
    assert EspeakVoice("") in ESPEAK_HELDOUT and all(v.variant for v in ESPEAK_TRAIN)
    held_variants = {v.variant for v in ESPEAK_HELDOUT}
    assert not held_variants & {v.variant for v in ESPEAK_TRAIN}
    a = espeak_synthesize("あいうえお。", voice=EspeakVoice("f3"))
    b = espeak_synthesize("あいうえお。", voice=EspeakVoice("m3"))
    assert len(a.samples) != len(b.samples) or not np.allclose(a.samples, b.samples)


def test_unknown_voice_is_a_clear_error() -> None:
    with pytest.raises(SpeechError, match="no voice 'ja\\+nosuchvoice'"):
        espeak_synthesize("あ。", voice=EspeakVoice("nosuchvoice"))
    with pytest.raises(SpeechError, match=r"rate must be 80\.\.450"):
        espeak_synthesize("あ。", voice=EspeakVoice("f3", rate=20))
