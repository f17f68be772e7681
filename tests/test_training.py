"""Training the analyser (issue 32.1): what the network is fitted on is what it later sees.

The mean normalisation is applied in two places - to whole training utterances and, frame by
frame, in the streaming analyser - so these check that the two give the same features, and
that a tiny model trained here carries its normalisation and reads its own training voice.
"""

from __future__ import annotations

import numpy as np

from facelab.stimuli.speech.analyser import analyze, features, raw_features
from facelab.stimuli.speech.natural import NaturalClip, vowel_cores
from facelab.stimuli.speech.track import VOWELS
from facelab.stimuli.speech.training import (
    TRAIN_VARIANTS,
    frame_labels,
    natural_utterances,
    speak,
    train,
    training_matrix,
)

SENTENCES = ("あおいうみがみえる。", "えきのまえでまつ。")


def test_a_trained_model_carries_its_normalisation_and_training_sees_what_analysis_sees() -> None:
    model = train(
        sentences=SENTENCES,
        variants=TRAIN_VARIANTS[:2],
        rng=np.random.default_rng(5),
        per_sentence=2,
        drills=("あ。い。う。え。お。",),
        hidden=16,
    )
    norm = model.normalisation
    assert norm is not None and norm.prior.shape == (12,)
    assert "mean normalisation" in model.info["trained_on"]
    # one utterance through the training path and through the analyser's features()
    speech = speak(SENTENCES[0], TRAIN_VARIANTS[0])
    times, seen = features(speech.samples, sample_rate=speech.sample_rate, normalisation=norm)
    raw = raw_features(speech.samples, sample_rate=speech.sample_rate)[1]
    labels = frame_labels(speech.phones, times).astype(str)
    x, y = training_matrix([(raw, labels)], normalisation=norm)
    keep = (labels != "") & (raw[:, 0] > -50.0)
    assert np.allclose(x, seen[keep, 1:]) and list(y) == list(labels[keep])
    # the normalisation changes the features (else it would not need carrying)
    plain, _ = training_matrix([(raw, labels)], normalisation=None)
    assert np.abs(plain - x).max() > 0.1
    # and the model reads the vowels of a sentence its training voices said, at the filters
    # it was trained with (this tiny model's confidence is no guide to a warp search)
    track = analyze(
        speech.samples, sample_rate=speech.sample_rate, model=model, warp=1.0
    ).compensated()
    heard = np.argmax(track.vowels(), axis=1)
    right = total = 0
    for p in speech.phones:
        if p.phoneme in VOWELS and p.end - p.start > 0.05:
            sel = (track.times > p.start + 0.02) & (track.times < p.end - 0.02)
            right += int(np.sum(heard[sel] == VOWELS.index(p.phoneme)))
            total += int(sel.sum())
    assert total > 20 and right / total > 0.8


def test_natural_clips_also_enter_as_a_lower_voice_with_their_cores_moved_along() -> None:
    speech = speak(SENTENCES[0], TRAIN_VARIANTS[0])
    clip = NaturalClip(
        SENTENCES[0],
        "mei",
        1.0,
        speech.samples,
        speech.sample_rate,
        vowel_cores(speech.phones),
        labelled_by="alignment",
    )
    rng = np.random.default_rng(3)
    plain = natural_utterances([clip], rng=rng)
    assert len(plain) == 2  # warp 1 and one random warp
    lowered = natural_utterances([clip], rng=rng, lower_range=(0.8, 0.8))
    assert len(lowered) == 3
    (raw, labels), (raw_low, labels_low) = lowered[0], lowered[2]
    # read at 0.8 of its rate the clip lasts 1.25 times as long, and so do its labelled cores
    assert abs(len(raw_low) / len(raw) - 1.25) < 0.01
    n, n_low = np.sum(labels != ""), np.sum(labels_low != "")
    assert n > 20 and abs(n_low / n - 1.25) < 0.1

    # the cores keep their vowels, in order: the label runs are the same
    def runs(lab: np.ndarray) -> list[str]:
        kept = [v for v in lab if v]
        return [v for k, v in enumerate(kept) if k == 0 or kept[k - 1] != v]

    assert runs(labels_low) == runs(labels)
    # and the labelled frames are the moved cores: each core's middle frame is labelled
    times_low = np.arange(len(raw_low)) * 0.01
    for lo, hi, _ in clip.cores:
        mid = (lo + hi) / 2 * 1.25
        assert labels_low[int(np.argmin(np.abs(times_low - mid)))] != ""
