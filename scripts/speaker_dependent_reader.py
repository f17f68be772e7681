"""How readable are a Kokoro voice's vowels to a reader that knows the voice? (README, "Natural
voices"; needs ``facelab[training]``.)

A speaker-dependent reference for the speaker-independent analyser: an RBF support-vector
classifier on the raw cepstra c1..c12 of +-3 frames around each vowel-core frame, trained on
the voice's *own* material and tested on other material of the same voice:

* syllables spoken alone (isolated vowels, na-row, ma-row at speeds 0.8 / 1.0 / 1.2): trained
  at two speeds, tested at the third (the same syllables, heard at other speeds); and trained
  on two rows, tested on the third (vowels of syllables it has not heard);
* the corpus's held-out sentences: trained on every other sentence, tested on the rest.

Prints the share of vowel-core frames read right per voice. The three readings differ in
how much and what the reader was trained on, not only in how distinct the vowels are: they
bound nothing. Not part of facelab; a diagnostic of the material
(``python scripts/speaker_dependent_reader.py [VOICE ...]``).
"""

from __future__ import annotations

import sys
import warnings

import numpy as np
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC

from facelab.stimuli.speech.analyser import raw_features
from facelab.stimuli.speech.natural import (
    NATURAL_HELDOUT,
    NATURAL_TRAIN,
    core_frames,
    natural_sentences,
    natural_syllables,
)
from facelab.stimuli.speech.training import corpus

CONTEXT = 3  # frames each side


def frames(clip) -> tuple[np.ndarray, np.ndarray]:
    times, feats = raw_features(clip.samples, sample_rate=clip.sample_rate)
    ceps = np.pad(feats[:, 1:], ((CONTEXT, CONTEXT), (0, 0)), mode="edge")
    stacked = np.hstack([ceps[i : i + len(feats)] for i in range(2 * CONTEXT + 1)])
    idx, vowel = core_frames(times, clip)
    return stacked[idx], vowel


def read(groups: list[list]) -> float:
    """Each group tested once, the reader trained on the others; pooled share right."""
    right = total = 0
    for k, test in enumerate(groups):
        train = [f for j, g in enumerate(groups) if j != k for f in g]
        model = make_pipeline(StandardScaler(), SVC(C=10.0)).fit(
            np.vstack([x for x, _ in train]), np.concatenate([y for _, y in train])
        )
        y = np.concatenate([y for _, y in test])
        right += int((model.predict(np.vstack([x for x, _ in test])) == y).sum())
        total += len(y)
    return right / total


def main(voices: list[str]) -> None:
    warnings.filterwarnings("ignore")
    _, held = corpus()
    for voice in voices:
        syllables = [(c.text, c.speed, frames(c)) for c in natural_syllables([voice])]
        rows = [[f for text, _, f in syllables if text.rstrip("。") in row]
                for row in ("あいうえお", "なにぬねの", "まみむめも")]  # fmt: skip
        speeds = [[f for _, speed, f in syllables if speed == s]
                  for s in sorted({speed for _, speed, _ in syllables})]  # fmt: skip
        sentences = [frames(c) for c in natural_sentences([voice], sentences=held)]
        halves = [sentences[0::2], sentences[1::2]]
        print(f"{voice}: syllables (a speed left out) {read(speeds):.3f}, "
              f"(a row left out) {read(rows):.3f}, sentences (halves) {read(halves):.3f}")


if __name__ == "__main__":
    main(sys.argv[1:] or [*NATURAL_HELDOUT, *NATURAL_TRAIN])
