"""Training and evaluation of the viseme analyser on OpenJTalk speech with exact timing.

Corpus: ``stimuli/data/corpus_ja.txt`` - the first 43 sentences train, the last 16 are held
out. Voices: the mei HTS voice in variants of speed, pitch and all-pass constant; training
and held-out variants use different values, so evaluation is on unseen sentences *and*
unseen voice settings. Labels come from the OpenJTalk trace (the audio was generated from
those durations), so they are exact up to the voice's 5 ms frame.

Rebuild the shipped model with ``python -m stimuli.viseme_training`` (about a minute).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facelab.errors import VisemeError
from facelab.resources import package_file
from facelab.stimuli.speech import Phone, Speech, synthesize
from facelab.stimuli.visemes import (
    HOP_S,
    MODEL_PATH,
    VOWELS,
    StreamingAnalyzer,
    VisemeModel,
    VisemeTrack,
    align_phones,
    analyze,
    calibrate,
    features,
    from_phonemes,
    phoneme_viseme,
)

__all__ = [
    "FAR_VARIANTS",
    "HELDOUT_VARIANTS",
    "TRAIN_VARIANTS",
    "Variant",
    "build_pylipsync_templates",
    "corpus",
    "evaluate",
    "frame_labels",
    "per_voice",
    "train",
]

CORPUS = package_file("facelab.stimuli", "data", "corpus_ja.txt")
N_TRAIN = 43
SPEECH_CLASSES = ("PP", "FF", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E", "ih", "oh", "ou")


@dataclass(frozen=True)
class Variant:
    speed: float
    pitch_halftones: float
    alpha: float

    def label(self) -> str:
        return f"r{self.speed:g}_fm{self.pitch_halftones:+g}_a{self.alpha:g}"


TRAIN_VARIANTS = tuple(
    Variant(s, p, a)
    for s, p, a in [
        (1.0, 0, 0.55),
        (0.85, -4, 0.50),
        (1.2, 4, 0.60),
        (1.0, -6, 0.58),
        (0.9, 6, 0.52),
        (1.1, 0, 0.50),
        (1.0, 2, 0.60),
        (0.95, -2, 0.53),
    ]
)
HELDOUT_VARIANTS = tuple(
    Variant(s, p, a)
    for s, p, a in [
        (0.95, 2, 0.53),  # none equals a training setting
        (0.92, -3, 0.54),
        (1.15, 3, 0.57),
        (1.05, 5, 0.51),
        (0.88, -5, 0.59),
    ]
)


def corpus() -> tuple[list[str], list[str]]:
    """(training sentences, held-out sentences)."""
    lines = [ln.strip() for ln in CORPUS.read_text(encoding="utf-8").splitlines()]
    sentences = [ln for ln in lines if ln and not ln.startswith("#")]
    return sentences[:N_TRAIN], sentences[N_TRAIN:]


def _synth(text: str, variant: Variant) -> Speech:
    return synthesize(
        text, speed=variant.speed, pitch_halftones=variant.pitch_halftones, alpha=variant.alpha
    )


def frame_labels(
    phones: Sequence[Phone], times: np.ndarray, *, guard_s: float = 0.01
) -> np.ndarray:
    """Class label per frame time ('' where unusable: boundaries within ``guard_s``, devoiced
    vowels, geminate closures, silence)."""
    labels = np.full(len(times), "", dtype=object)
    for phone in phones:
        sel = (times >= phone.start + guard_s) & (times < phone.end - guard_s)
        if phone.phoneme in ("A", "I", "U", "E", "O", "cl", "sil", "pau"):
            continue
        labels[sel] = phoneme_viseme(phone.phoneme)
    return labels


def train(
    *,
    sentences: Iterable[str],
    variants: Sequence[Variant],
    temperature: float = 2.0,
    prior_power: float = 0.5,
    ridge: float = 1e-3,
    rng: np.random.Generator,
    per_sentence: int = 4,
) -> VisemeModel:
    """Fit the linear-discriminant model on synthesised speech.

    Each sentence is spoken in ``per_sentence`` variants drawn from ``variants``. Priors are
    the class frequencies to the power ``prior_power`` (flattened so rare visemes can win).
    """
    xs, ys = [], []
    for text in sentences:
        for vi in rng.choice(len(variants), size=min(per_sentence, len(variants)), replace=False):
            speech = _synth(text, variants[vi])
            times, x = features(speech.samples, sample_rate=speech.sample_rate)
            labels = frame_labels(speech.phones, times)
            keep = (labels != "") & (x[:, 0] > -50.0)
            xs.append(x[keep])
            ys.append(labels[keep])
    x_all, y_all = np.vstack(xs)[:, 1:], np.concatenate(ys)
    classes = tuple(c for c in SPEECH_CLASSES if np.any(y_all == c))
    means = np.stack([x_all[y_all == c].mean(axis=0) for c in classes])
    centred = x_all - means[[classes.index(c) for c in y_all]]
    cov = centred.T @ centred / (len(x_all) - len(classes))
    cov += ridge * np.trace(cov) / cov.shape[0] * np.eye(cov.shape[0])
    counts = np.array([np.sum(y_all == c) for c in classes], dtype=float)
    log_priors = prior_power * np.log(counts / counts.sum())
    return VisemeModel(
        classes=classes,
        means=means,
        precision=np.linalg.inv(cov),
        log_priors=log_priors,
        temperature=temperature,
        info={
            "trained_on": f"{len(sentences)} sentences x {per_sentence} of {len(variants)} "
            "mei variants",
            "frames": len(x_all),
            "class_frames": dict(zip(classes, counts.astype(int).tolist(), strict=True)),
        },
    )


@dataclass
class Evaluation:
    """Frame-level vowel accuracy of tracks against the OpenJTalk timing."""

    confusion: np.ndarray  # (5, 5) true x predicted, all vowel frames
    core_correct: int = 0
    core_total: int = 0

    @property
    def all_accuracy(self) -> float:
        return float(np.trace(self.confusion) / max(self.confusion.sum(), 1))

    @property
    def core_accuracy(self) -> float:
        return self.core_correct / max(self.core_total, 1)


def score_track(
    ev: Evaluation,
    track: VisemeTrack | np.ndarray,
    times: np.ndarray,
    phones: Sequence[Phone],
    *,
    core: float = 0.6,
) -> None:
    """Add one utterance's frames to ``ev`` (vowel argmax among a i u e o)."""
    vowels = track.vowels() if isinstance(track, VisemeTrack) else track
    pred = np.argmax(vowels, axis=1)
    for phone in phones:
        if phone.phoneme not in VOWELS:
            continue
        truth = VOWELS.index(phone.phoneme)
        sel = np.nonzero((times >= phone.start) & (times < phone.end))[0]
        for i in sel:
            ev.confusion[truth, pred[i]] += 1
        margin = (phone.end - phone.start) * (1 - core) / 2
        core_sel = (times >= phone.start + margin) & (times < phone.end - margin)
        ev.core_total += int(core_sel.sum())
        ev.core_correct += int(np.sum(pred[core_sel] == truth))


#: Voice settings far outside the training grid (pitch and all-pass beyond every training
#: variant): the stand-in for "voices not used in training" - every variant is still the one
#: OpenJTalk voice (mei); no other Japanese voice is installable offline here.
FAR_VARIANTS = (
    Variant(1.0, -11, 0.44),
    Variant(1.0, 10, 0.63),
    Variant(1.0, -6, 0.61),
    Variant(1.0, 6, 0.47),
)


def per_voice(model: VisemeModel, *, sentences: Sequence[str], variants: Sequence[Variant]) -> dict:
    """Per voice setting: vowel accuracy (all frames) audio-only uncalibrated, after
    ``calibrate()`` on that voice's あ。い。う。え。お。, and from ``align()`` with the text, plus
    the median vowel-onset error of the alignment (ms)."""
    out = {}
    for variant in variants:
        cal_rec = _synth("あ。い。う。え。お。", variant)
        try:
            tuned = calibrate(model, cal_rec.samples, sample_rate=cal_rec.sample_rate)
        except VisemeError as exc:
            tuned = None
            cal_note = str(exc)
        evs = {
            k: Evaluation(np.zeros((5, 5), dtype=int)) for k in ("audio", "calibrated", "aligned")
        }
        onsets = []
        for text in sentences:
            speech = _synth(text, variant)
            track = analyze(
                speech.samples, sample_rate=speech.sample_rate, model=model
            ).compensated()
            score_track(evs["audio"], track, track.times, speech.phones)
            if tuned is not None:
                t2 = analyze(
                    speech.samples, sample_rate=speech.sample_rate, model=tuned
                ).compensated()
                score_track(evs["calibrated"], t2, t2.times, speech.phones)
            res = align_phones(speech.samples, sample_rate=speech.sample_rate, text=text)
            t3 = from_phonemes(res.phones, duration_s=speech.duration_s)
            score_track(evs["aligned"], t3, t3.times, speech.phones)
            onsets += [
                abs(a.start - b.start)
                for a, b in zip(speech.phones, res.phones, strict=True)
                if a.phoneme in VOWELS
            ]
        out[variant.label()] = {
            "audio_only_uncalibrated": round(evs["audio"].all_accuracy, 4),
            "audio_only_calibrated": (
                round(evs["calibrated"].all_accuracy, 4) if tuned is not None else cal_note
            ),
            "aligned_with_text": round(evs["aligned"].all_accuracy, 4),
            "aligned_vowel_onset_error_ms_median": round(1000 * float(np.median(onsets)), 1),
        }
    return out


def evaluate(
    model: VisemeModel,
    *,
    sentences: Sequence[str],
    variants: Sequence[Variant],
    pylipsync_templates: Path | None = None,
) -> dict:
    """Benchmark numbers (see ``facelab bench visemes``)."""
    ours = Evaluation(np.zeros((5, 5), dtype=int))
    theirs = Evaluation(np.zeros((5, 5), dtype=int)) if pylipsync_templates else None
    audio_s = 0.0
    analyse_s = 0.0
    lags = []
    analyzer = _pylipsync(pylipsync_templates) if pylipsync_templates else None
    for text in sentences:
        for variant in variants:
            speech = _synth(text, variant)
            audio_s += speech.duration_s
            t0 = time.perf_counter()
            track = analyze(speech.samples, sample_rate=speech.sample_rate, model=model)
            analyse_s += time.perf_counter() - t0
            comp = track.compensated()
            score_track(ours, comp, comp.times, speech.phones)
            lags.append(_vowel_energy_lag(comp, speech.phones))
            if analyzer is not None and theirs is not None:
                times, vowels = _pylipsync_vowels(analyzer, speech)
                score_track(theirs, vowels, times, speech.phones)
    stream = StreamingAnalyzer(sample_rate=48_000, model=model)
    out = {
        "sentences": len(sentences),
        "variants": [v.label() for v in variants],
        "audio_s": round(audio_s, 2),
        "facelab": {
            "vowel_accuracy_all_frames": round(ours.all_accuracy, 4),
            "vowel_accuracy_cores": round(ours.core_accuracy, 4),
            "frames_all": int(ours.confusion.sum()),
            "frames_cores": ours.core_total,
            "confusion_rows_true_cols_pred": {
                "labels": list(VOWELS),
                "counts": ours.confusion.tolist(),
            },
            "real_time_factor_offline": round(audio_s / analyse_s, 1),
            "streaming_latency_ms": round(1000 * stream.latency_s, 1),
            "vowel_energy_lag_ms": {
                "median": float(np.median(lags)),
                "min": float(np.min(lags)),
                "max": float(np.max(lags)),
            },
        },
    }
    if theirs is not None:
        out["pylipsync"] = {
            "templates": "built by pylipsync from the same training audio's vowel segments",
            "vowel_accuracy_all_frames": round(theirs.all_accuracy, 4),
            "vowel_accuracy_cores": round(theirs.core_accuracy, 4),
            "confusion_rows_true_cols_pred": {
                "labels": list(VOWELS),
                "counts": theirs.confusion.tolist(),
            },
        }
    return out


def _vowel_energy_lag(track: VisemeTrack, phones: Sequence[Phone]) -> float:
    """Lag (ms) maximising the cross-correlation of the audio track's vowel energy with the
    text-driven (OpenJTalk timing) track's; positive = audio track late."""
    from facelab.stimuli.visemes import from_phonemes

    ref = from_phonemes(phones, smoothing_s=0.02, duration_s=track.times[-1])
    n = min(len(ref.times), len(track.times))
    a = track.vowels()[:n].sum(axis=1)
    b = ref.vowels()[:n].sum(axis=1)
    a, b = a - a.mean(), b - b.mean()
    lags = np.arange(-10, 11)
    # corr[k] pairs a[t + k] with b[t]: a peak at k > 0 means the audio track is late
    corr = np.array(
        [np.dot(a[max(0, k) : n + min(0, k)], b[max(0, -k) : n - max(0, k)]) for k in lags]
    )
    i = int(np.argmax(corr))
    offset = 0.0
    if 0 < i < len(lags) - 1:  # parabolic interpolation between frames
        den = corr[i - 1] - 2 * corr[i] + corr[i + 1]
        offset = 0.5 * (corr[i - 1] - corr[i + 1]) / den if den else 0.0
    return float((lags[i] + offset) * HOP_S * 1000)


# --------------------------------------------------------------------------- pylipsync comparison


def build_pylipsync_templates(
    folder: Path, *, sentences: Sequence[str], variants: Sequence[Variant]
) -> Path:
    """Write vowel-segment WAVs of the training audio into pylipsync's folder layout
    (aa/ee/ih/oh/ou/silence) so it builds its templates from the same data as facelab."""
    import soundfile as sf

    names = {"a": "aa", "i": "ih", "u": "ou", "e": "ee", "o": "oh"}
    for name in [*names.values(), "silence"]:
        (folder / "audio" / name).mkdir(parents=True, exist_ok=True)
    count = 0
    for si, text in enumerate(sentences):
        speech = _synth(text, variants[si % len(variants)])
        for pi, phone in enumerate(speech.phones):
            if phone.phoneme in names and phone.end - phone.start >= 0.06:
                a, b = int(phone.start * speech.sample_rate), int(phone.end * speech.sample_rate)
                sf.write(
                    folder / "audio" / names[phone.phoneme] / f"{si}_{pi}.wav",
                    speech.samples[a:b],
                    speech.sample_rate,
                )
                count += 1
        sil = speech.samples[: int(0.15 * speech.sample_rate)] + 1e-4 * np.random.default_rng(
            si
        ).normal(size=int(0.15 * speech.sample_rate))
        sf.write(
            folder / "audio" / "silence" / f"{si}.wav", sil.astype(np.float32), speech.sample_rate
        )
    return folder


def _pylipsync(folder: Path):
    from pylipsync import PhonemeAnalyzer

    return PhonemeAnalyzer(
        phoneme_templates_path=str(folder / "template.json"),
        audio_templates_path=str(folder / "audio"),
    )


def _pylipsync_vowels(analyzer, speech: Speech) -> tuple[np.ndarray, np.ndarray]:
    segs = analyzer.extract_phoneme_segments(
        speech.samples.astype(np.float32), speech.sample_rate, fps=100, return_seconds=True
    )
    order = ["aa", "ih", "ou", "ee", "oh"]
    vowels = np.array(
        [
            [next((p.target for p in seg.phonemes if p.name == name), 0.0) for name in order]
            for seg in segs
        ]
    )
    times = np.array([(seg.start + seg.end) / 2 for seg in segs])
    return times, vowels


def main() -> None:
    rng = np.random.default_rng(20261122)
    train_sentences, _ = corpus()
    t0 = time.perf_counter()
    model = train(sentences=train_sentences, variants=TRAIN_VARIANTS, rng=rng)
    model.save(MODEL_PATH)
    print(
        f"trained on {model.info['frames']} frames in {time.perf_counter() - t0:.1f} s; "
        f"classes {', '.join(model.classes)} -> {MODEL_PATH}"
    )


if __name__ == "__main__":
    main()
