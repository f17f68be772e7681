"""Alignment of a recording to its known words: a TTS reference of the text, dynamic time
warping over the analyser's posteriorgram, and the reference's phoneme times carried over.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace

import numpy as np

from facelab.bounded_memo import BoundedMemo
from facelab.errors import VisemeError
from facelab.stimuli.speech.analyser import VisemeModel, analysis_input, default_model, features
from facelab.stimuli.speech.features import HOP_S
from facelab.stimuli.speech.track import FPS, VisemeTrack, from_phonemes

__all__ = [
    "Alignment",
    "align",
    "align_phones",
]

# --------------------------------------------------------------------------- alignment

#: A stretch of speech longer than this that only one side has is a text/audio mismatch.
MISMATCH_S = 0.6
#: The largest local speaking-rate ratio between the recording and the TTS reference.
MAX_SLOPE = 3.5


@dataclass(frozen=True)
class Alignment:
    """Phones of ``text`` timed on a recording (:func:`align_phones`): ``phones`` (Phone, s),
    ``words`` and ``accents`` of the front end moved onto the recording's time, the DTW
    ``mean_cost``, the reference (TTS) duration, and ``reversed_cost``: the mean cost of the
    same DTW against the reference played backwards (the same sounds and speaker, their
    order lost) - the yardstick of :attr:`order_fit`."""

    phones: tuple
    words: tuple
    accents: tuple
    mean_cost: float
    reference_s: float
    reversed_cost: float = float("nan")

    @property
    def order_fit(self) -> float:
        """``mean_cost / reversed_cost``: how much better the recording matches its text in
        the text's order than in reverse (NaN without a yardstick). The cost itself depends
        on the voice (a voice unlike the reference costs more either way); the ratio much
        less. Measured on 16 sentences (facelab.stimuli.checks.run_checks.TRANSCRIPT_ORDER_FIT):
        recordings of their own text 0.02-0.45 in OpenJTalk, 0.49-0.88 in three natural
        voices, 0.64-0.98 in eSpeak NG (whose Japanese the analyser reads worst); other
        words, or the text said twice, 0.67-1.16."""
        return self.mean_cost / self.reversed_cost if self.reversed_cost > 0 else float("nan")


#: Log posteriors below this count as this (one class's absence is not evidence to align on).
POSTERIOR_FLOOR = -8.0
#: Weight of the level column in the posteriorgram (per 10 dB below the loud level).
LEVEL_WEIGHT = 3.0


def _posteriorgram(x: np.ndarray, model: VisemeModel) -> np.ndarray:
    """(T, C + 1) DTW features from stacked features x (T, 1 + D): floored log posteriors
    and the level in 10 dB steps from the utterance's 95th percentile, weighted."""
    logits = model.logits(x[:, 1:])
    logp = logits - np.logaddexp.reduce(logits, axis=1, keepdims=True)
    level = (x[:, :1] - np.percentile(x[:, 0], 95)) / 10.0
    return np.column_stack([np.maximum(logp, POSTERIOR_FLOOR), LEVEL_WEIGHT * level])


def _frame_level(samples: np.ndarray, sample_rate: int, n: int) -> np.ndarray:
    hop = int(sample_rate * HOP_S)
    padded = np.concatenate([samples, np.zeros(hop * (n + 1))])[: hop * n]
    rms = np.sqrt((padded.reshape(n, hop).astype(np.float64) ** 2).mean(axis=1))
    return 20 * np.log10(rms + 1e-9)


#: alignments kept per process (:func:`align_phones` with the default model): ``facelab
#: render`` aligns each recording while it checks the protocol's files, then for its clips,
#: in the same order - so every recording of a large study must fit (an alignment holds a
#: few kB of phones, words and accents)
_memo: BoundedMemo[Alignment | str] = BoundedMemo(max_items=8192)


def align_phones(
    samples: np.ndarray, *, sample_rate: int, text: str, model: VisemeModel | None = None
) -> Alignment:
    """Time the phonemes of ``text`` on a recording of it (see :func:`_align_phones`); with
    the default model, a recording and text aligned before in this process are not aligned
    again (nor is a disagreement found again: the same error is raised)."""
    if model is not None:
        return _align_phones(samples, sample_rate=sample_rate, text=text, model=model)
    x = np.ascontiguousarray(samples)
    key = (hashlib.sha1(x.tobytes()).hexdigest(), str(x.dtype), int(sample_rate), text)
    kept = _memo.get(key)
    if kept is None:
        try:
            kept = _align_phones(x, sample_rate=sample_rate, text=text)
        except VisemeError as exc:
            kept = str(exc)
        _memo.put(key, kept)
    if isinstance(kept, str):
        raise VisemeError(kept)
    return kept


def _align_phones(
    samples: np.ndarray, *, sample_rate: int, text: str, model: VisemeModel | None = None
) -> Alignment:
    """Time the phonemes of ``text`` on a recording of it.

    The text is synthesised by OpenJTalk (its phone timeline known exactly); both signals
    are turned into posteriorgrams - the analyser's log posteriors of the 13 viseme classes
    per frame (floored at ``POSTERIOR_FLOOR``), plus the frame level relative to the
    utterance's loud level - which are speaker-independent as far as the analyser is, and
    aligned by DTW (:func:`facelab.stimuli.speech.dtw.dtw_path`); each reference phone boundary
    moves along the path onto the recording. (Cepstra normalised per utterance, the first
    version, kept too much of the speaker: on eSpeak voices 0.44-0.83 of vowel frames.)
    Where one side holds more than ``MISMATCH_S`` of speech that the other lacks (a long
    horizontal or vertical run of the path over loud frames), the text and the audio
    disagree and :class:`VisemeError` says where."""
    from facelab.stimuli.speech.audio import Phone
    from facelab.stimuli.speech.dtw import dtw_path
    from facelab.stimuli.speech.tts import synthesize

    samples, rate = analysis_input(samples, sample_rate=sample_rate)
    ref = synthesize(text, sample_rate=rate)
    model = model or default_model()
    _, xa = features(samples, sample_rate=rate, normalisation=model.normalisation)
    _, xr = features(ref.samples, sample_rate=rate, normalisation=model.normalisation)
    level_a = _frame_level(samples, rate, len(xa))
    level_r = _frame_level(ref.samples, rate, len(xr))
    loud_a = level_a > np.percentile(level_a, 95) - 25
    loud_r = level_r > np.percentile(level_r, 95) - 25
    # leading and trailing silence stay out of the DTW (their lengths are arbitrary): the
    # speech spans are aligned, the silences before and after map linearly
    ra, rb = _speech_span(loud_r)
    aa, ab = _speech_span(loud_a)
    post_r, post_a = _posteriorgram(xr, model)[ra:rb], _posteriorgram(xa, model)[aa:ab]
    path, mean_cost = dtw_path(post_r, post_a)
    path = path + np.array([ra, aa])
    _check_runs(path, loud_r, loud_a)
    # reference frame -> recording frame (median of the path's matches), monotone
    mapped = np.zeros(len(xr))
    for i in range(ra, rb):
        mapped[i] = np.median(path[path[:, 0] == i, 1])
    mapped[:ra] = np.arange(ra) * aa / max(ra, 1)
    tail = len(xr) - rb
    mapped[rb:] = ab - 1 + np.arange(1, tail + 1) * (len(xa) - ab) / max(tail, 1)
    mapped = np.maximum.accumulate(mapped)
    _check_slope(mapped, loud_r, loud_a)
    end_a = len(samples) / rate

    def move(t: float) -> float:
        k = t * FPS
        return float(min(end_a, np.interp(k, np.arange(len(mapped)), mapped) / FPS))

    phones = tuple(Phone(p.phoneme, move(p.start), move(p.end)) for p in ref.phones)
    words = tuple(
        w if w.morae == 0 else type(w)(w.surface, w.reading, w.pos, w.morae, move(w.start),
                                       move(w.end))
        for w in ref.words
    )  # fmt: skip
    accents = tuple(
        replace(a, start=move(a.start), end=move(a.end), peak=move(a.peak)) for a in ref.accents
    )
    _, reversed_cost = dtw_path(post_r[::-1], post_a)
    return Alignment(phones, words, accents, mean_cost, ref.duration_s, reversed_cost)


def _speech_span(loud: np.ndarray, *, margin: int = 5) -> tuple[int, int]:
    """[first, last + 1) frames of speech (loud) widened by ``margin`` frames each side."""
    idx = np.flatnonzero(loud)
    if len(idx) == 0:
        return 0, len(loud)
    return max(0, int(idx[0]) - margin), min(len(loud), int(idx[-1]) + 1 + margin)


def _check_slope(mapped: np.ndarray, loud_ref: np.ndarray, loud_rec: np.ndarray) -> None:
    """A half-second of the text's speech stretched over more than MAX_SLOPE times as much
    loud recording (extra speech), or squeezed into less than 1/MAX_SLOPE (missing speech),
    both relative to the whole utterance's rate (loud recording frames per loud reference
    frame, within 1/2..2): a speaker who is faster or slower throughout is not a mismatch."""
    w = int(0.5 * FPS)
    rate = float(np.clip(loud_rec.sum() / max(loud_ref.sum(), 1), 0.5, 2.0))
    for i in range(0, len(mapped) - w, 5):
        if loud_ref[i : i + w].mean() < 0.5:
            continue  # pauses may stretch freely
        a, b = int(mapped[i]), int(mapped[i + w])
        loud_span = int(loud_rec[a : b + 1].sum())
        if loud_span > MAX_SLOPE * w * rate:
            raise VisemeError(
                f"text and audio disagree: the recording has about {(loud_span - w) / FPS:.1f} s "
                f"of speech the text does not have near {a / FPS:.2f} s of the recording"
            )
        if b - a < w * rate / MAX_SLOPE:
            raise VisemeError(
                "text and audio disagree: the text has words the recording does not say "
                f"near {a / FPS:.2f} s of the recording"
            )


def _check_runs(path: np.ndarray, loud_ref: np.ndarray, loud_rec: np.ndarray) -> None:
    limit = int(MISMATCH_S * FPS)
    # speech on one side matched to silence on the other, for longer than MISMATCH_S
    for side, loud, other, what in (
        (
            1,
            loud_rec,
            loud_ref,
            "the recording has about {:.1f} s of speech the text does not have",
        ),
        (0, loud_ref, loud_rec, "the text has words the recording does not say (about {:.1f} s)"),
    ):
        lonely = loud[path[:, side]] & ~other[path[:, 1 - side]]
        frames = np.unique(path[lonely, side])
        if len(frames):
            breaks = np.flatnonzero(np.diff(frames) > 3)
            for a, b in zip(np.r_[0, breaks + 1], np.r_[breaks, len(frames) - 1], strict=True):
                if frames[b] - frames[a] + 1 > limit:
                    at = path[np.flatnonzero(path[:, side] == frames[a])[0], 1] / FPS
                    raise VisemeError(
                        "text and audio disagree: "
                        + what.format((frames[b] - frames[a] + 1) / FPS)
                        + f" near {at:.2f} s of the recording"
                    )
    for axis, loud, what in (
        (0, loud_rec, "the recording has about {:.1f} s of speech the text does not have"),
        (1, loud_ref, "the text has words the recording does not say (about {:.1f} s)"),
    ):
        # runs where one index stays fixed while the other advances over loud frames
        fixed = path[:, axis]
        moving = path[:, 1 - axis]
        start = 0
        for k in range(1, len(path) + 1):
            if k == len(path) or fixed[k] != fixed[start]:
                run = moving[start:k]
                n_loud = int(loud[run].sum()) if len(run) > 1 else 0
                if n_loud > limit:
                    where = path[start, 1] / FPS
                    raise VisemeError(
                        "text and audio disagree: "
                        + what.format(n_loud / FPS)
                        + f" near {where:.2f} s of the recording"
                    )
                start = k


def align(
    samples: np.ndarray,
    *,
    sample_rate: int,
    text: str,
    smoothing_s: float = 0.04,
    model: VisemeModel | None = None,
) -> VisemeTrack:
    """The viseme track of a recording whose words are known: the text's phonemes aligned to
    the audio (:func:`align_phones`) and turned into visemes (:func:`from_phonemes`), frames
    every 10 ms over the whole recording - the same track type as :func:`analyze`."""
    result = align_phones(samples, sample_rate=sample_rate, text=text, model=model)
    duration = len(np.asarray(samples)) / sample_rate
    return from_phonemes(result.phones, smoothing_s=smoothing_s, duration_s=duration)


