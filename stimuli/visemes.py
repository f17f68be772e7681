"""Viseme tracks: an audio-only 15-viseme analyser, the text-driven track, vowel isolation.

Output order is Oculus LipSync's: ``sil PP FF TH DD kk CH SS nn RR aa E ih oh ou``; the five
Japanese vowels a, i, u, e, o are ``aa, ih, ou, E, oh``.

The analyser (method and why)
-----------------------------
Per 10 ms frame: a 32 ms Hamming window centred on the frame time, pre-emphasis (0.97,
applied to the spectrum), mel filterbank
(40 bands, 60-7600 Hz, computed at the input's own rate so nothing is resampled), log, DCT
-> 12 cepstral coefficients (c1..c12, level independent) plus the log energy; stacked with the
frames 30 ms and 60 ms earlier (causal context, no extra latency). A small neural network
(one ReLU layer of 128 units, softmax) gives posteriors over the 13 viseme classes seen in
Japanese speech; a temperature softens them into blends, an absolute level gate (-50..-30
dBFS, as uLipSync) scales them, and ``sil`` takes the rest.

Speaker independence comes from the training data, not from a per-speaker step: two
synthesizers with exact phoneme times (OpenJTalk's statistical mei voice in 14 settings of
speed, pitch and all-pass constant, and eSpeak NG's formant voices in 29 variants at random
rates and pitches), every utterance also entered at a random mel-filter warp of 0.8..1.25
(vocal-tract-length augmentation) - see ``stimuli/viseme_training.py``. The network sees one
frame and its causal context, so the streaming analyser is speaker-independent from its first
frame. :func:`choose_warp` (vocal-tract-length normalisation chosen per utterance) remains
as an option (``warp="auto"``); on the shipped model it helps some voices and hurts others,
so it is off by default (``facelab bench visemes`` reports both).

Why this and not uLipSync's template matching: the network uses the same MFCC evidence but
learns which directions separate the classes across voices (uLipSync's L1/L2/cosine
distances treat every coefficient alike and fit one speaker), it yields probabilities
(blends) rather than ad-hoc scores, and it covers consonant visemes, which templates of five
vowels cannot. Calibration keeps uLipSync's idea - a short recording of the speaker's five
vowels - as an input bias and a regularised refit of the output layer (:func:`calibrate`).

Latency: in streaming, a frame needs audio up to 16 ms (half a window) after its time, and
the posteriors are smoothed by a one-pole filter (tau 10 ms, group delay ~6 ms):
``StreamingAnalyzer.latency_s`` is the sum. Offline the window is centred on the frame time,
so only the smoothing lag remains; ``VisemeTrack.latency_s`` states it and rendering removes
it (``compensated()``) so the mouth is not late.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path

import numpy as np
from scipy import signal
from scipy.fft import dct, rfft

from facelab.errors import VisemeError
from facelab.resources import package_file
from facelab.stimuli.arkit import OCULUS_VISEMES
from facelab.stimuli.speech import MIN_SAMPLE_RATE, resample

__all__ = [
    "VISEMES",
    "VOWELS",
    "VOWEL_VISEMES",
    "Alignment",
    "StreamingAnalyzer",
    "VisemeModel",
    "VisemeTrack",
    "align",
    "align_phones",
    "analyze",
    "calibrate",
    "choose_warp",
    "default_model",
    "from_phonemes",
    "isolate_vowels",
    "phoneme_viseme",
    "vowel_segments",
]

VISEMES: tuple[str, ...] = OCULUS_VISEMES
VOWELS: tuple[str, ...] = ("a", "i", "u", "e", "o")
VOWEL_VISEMES: tuple[str, ...] = ("aa", "ih", "ou", "E", "oh")
_VOWEL_INDEX = [VISEMES.index(v) for v in VOWEL_VISEMES]
MODEL_PATH = package_file("facelab.stimuli", "data", "viseme_model.json")
MODEL_FORMAT = "facelab-viseme-mlp-1"
FPS = 100.0


# --------------------------------------------------------------------------- the track


@dataclass(frozen=True)
class VisemeTrack:
    """Viseme weights over time.

    times : (T,) seconds, frame times (uniform, ``fps`` per second).
    weights : (T, 15) in [0, 1], columns in :data:`VISEMES` order, rows summing to 1.
    latency_s : how late the weights are relative to the audio at the frame times (the
        analyser's smoothing lag; 0 for text-driven tracks). ``compensated()`` removes it.
    """

    times: np.ndarray
    weights: np.ndarray
    names: tuple[str, ...] = VISEMES
    latency_s: float = 0.0
    warp: float = 1.0  # the mel-filter warp the analyser used (vocal-tract normalisation)

    @property
    def fps(self) -> float:
        return (
            FPS if len(self.times) < 2 else float(round(1.0 / (self.times[1] - self.times[0]), 6))
        )

    def vowels(self) -> np.ndarray:
        """(T, 5) intensities of a, i, u, e, o (the aa, ih, ou, E, oh columns)."""
        return self.weights[:, _VOWEL_INDEX]

    def compensated(self) -> VisemeTrack:
        """The track moved earlier by its latency (linear interpolation on the same times)."""
        if self.latency_s == 0:
            return self
        shifted = np.empty_like(self.weights)
        for j in range(self.weights.shape[1]):
            shifted[:, j] = np.interp(self.times + self.latency_s, self.times, self.weights[:, j])
        return replace(self, weights=shifted, latency_s=0.0)


# --------------------------------------------------------------------------- phonemes -> visemes

_CONSONANT_VISEME = {
    "p": "PP",
    "b": "PP",
    "m": "PP",
    "py": "PP",
    "by": "PP",
    "my": "PP",
    "f": "FF",
    "v": "FF",
    "t": "DD",
    "d": "DD",
    "ty": "DD",
    "dy": "DD",
    "k": "kk",
    "g": "kk",
    "ky": "kk",
    "gy": "kk",
    "kw": "kk",
    "gw": "kk",
    "s": "SS",
    "z": "SS",
    "sh": "CH",
    "ch": "CH",
    "j": "CH",
    "ts": "CH",
    "n": "nn",
    "ny": "nn",
    "N": "nn",
    "r": "RR",
    "ry": "RR",
    "y": "ih",
    "w": "ou",
    "h": "SS",
    "hy": "SS",
    "sil": "sil",
    "pau": "sil",
}


def phoneme_viseme(phoneme: str) -> str | None:
    """The viseme of an OpenJTalk phoneme (devoiced vowels map like voiced ones); None for
    ``cl`` (a geminate closure takes its shape from the context)."""
    if phoneme.lower() in VOWELS:
        return VOWEL_VISEMES[VOWELS.index(phoneme.lower())]
    if phoneme == "cl":
        return None
    if phoneme not in _CONSONANT_VISEME:
        raise VisemeError(f"unknown OpenJTalk phoneme {phoneme!r}")
    return _CONSONANT_VISEME[phoneme]


def from_phonemes(
    phones: Sequence,
    *,
    fps: float = FPS,
    smoothing_s: float = 0.04,
    duration_s: float | None = None,
) -> VisemeTrack:
    """The text-driven track from an OpenJTalk phoneme timeline.

    Each phone sets its viseme's target to 1 (devoiced vowels 0.4, ``h`` the following
    vowel's shape at 0.5, ``cl`` holds the previous shape, ``N`` before p/b/m is PP), sampled
    at frame times; coarticulation is a Gaussian blur of the targets with SD ``smoothing_s``
    (symmetric: a text-driven track may anticipate). ``sil`` takes the remainder.
    """
    if not phones:
        raise VisemeError("empty phoneme timeline")
    end = duration_s if duration_s is not None else phones[-1].end
    times = np.arange(int(np.floor(end * fps)) + 1) / fps
    targets = np.zeros((len(times), len(VISEMES)))
    for i, phone in enumerate(phones):
        ph = phone.phoneme
        weight = 1.0
        nxt = phones[i + 1].phoneme if i + 1 < len(phones) else "sil"
        if ph in ("A", "I", "U", "E", "O"):
            viseme, weight = phoneme_viseme(ph), 0.4
        elif ph in ("h", "hy") and nxt.lower() in VOWELS:
            viseme, weight = phoneme_viseme(nxt), 0.5
        elif ph == "N" and nxt in ("p", "b", "m", "py", "by", "my"):
            viseme = "PP"
        elif ph == "cl":
            viseme = "PP" if nxt in ("p", "b", "py", "by") else None
            if viseme is None:
                prev = phones[i - 1].phoneme if i else "sil"
                viseme, weight = phoneme_viseme(prev) or "sil", 0.5
        else:
            viseme = phoneme_viseme(ph)
        if viseme == "sil":
            continue
        sel = (times >= phone.start) & (times < phone.end)
        targets[sel, VISEMES.index(viseme)] = np.maximum(
            targets[sel, VISEMES.index(viseme)], weight
        )
    if smoothing_s > 0:
        sigma = smoothing_s * fps
        radius = int(np.ceil(4 * sigma))
        kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
        kernel /= kernel.sum()
        padded = np.pad(targets, ((radius, radius), (0, 0)))
        targets = np.stack(
            [np.convolve(padded[:, j], kernel, mode="valid") for j in range(targets.shape[1])],
            axis=1,
        )
    total = targets[:, 1:].sum(axis=1)
    over = total > 1
    targets[over, 1:] /= total[over, None]
    targets[:, 0] = 1 - targets[:, 1:].sum(axis=1)
    return VisemeTrack(times=times, weights=np.clip(targets, 0, 1))


# --------------------------------------------------------------------------- features

WINDOW_S = 0.032
HOP_S = 0.010
N_MELS = 40
N_CEPS = 12
CONTEXT = (0, 3, 6)  # frames back
MEL_RANGE_HZ = (60.0, 7600.0)


@cache
def _mel_bank(sample_rate: int, n_fft: int, warp: float = 1.0) -> np.ndarray:
    """Triangular mel filters; ``warp`` > 1 reads the spectrum at frequencies ``warp`` times
    higher (vocal-tract-length normalisation of a shorter tract), < 1 lower."""

    def hz_to_mel(f: np.ndarray | float) -> np.ndarray | float:
        return 1127.0 * np.log1p(np.asarray(f) / 700.0)

    lo, hi = (hz_to_mel(f) for f in MEL_RANGE_HZ)
    edges = 700.0 * np.expm1(np.linspace(lo, hi, N_MELS + 2) / 1127.0) * warp
    if edges[-1] > sample_rate / 2:
        raise VisemeError(
            f"warp {warp}: the mel filters would pass {sample_rate / 2:.0f} Hz, the Nyquist "
            f"frequency of {sample_rate} Hz audio"
        )
    freqs = np.fft.rfftfreq(n_fft, 1.0 / sample_rate)
    bank = np.zeros((N_MELS, len(freqs)))
    for m in range(N_MELS):
        left, centre, right = edges[m], edges[m + 1], edges[m + 2]
        up = (freqs - left) / (centre - left)
        down = (right - freqs) / (right - centre)
        bank[m] = np.clip(np.minimum(up, down), 0, None)
        bank[m] /= max(bank[m].sum(), 1e-12)
    return bank


@dataclass(frozen=True)
class _FrameGeometry:
    sample_rate: int
    win: int
    hop: int
    n_fft: int

    @classmethod
    def for_rate(cls, sample_rate: int) -> _FrameGeometry:
        if sample_rate < 16_000:
            raise VisemeError(
                f"sample rate {sample_rate} Hz is too low: the streaming analyser needs "
                ">= 16 kHz (the mel bands reach 7.6 kHz); analyze() resamples lower rates"
            )
        hop = sample_rate * HOP_S
        if abs(hop - round(hop)) > 1e-9:
            raise VisemeError(
                f"sample rate {sample_rate} Hz is not a multiple of 100 Hz (the streaming "
                "analyser's 10 ms hop); analyze() resamples such rates"
            )
        win = round(sample_rate * WINDOW_S)
        return cls(sample_rate, win, round(hop), 1 << (win - 1).bit_length())


@cache
def _emphasis(sample_rate: int, n_fft: int) -> np.ndarray:
    """|1 - 0.97 z^-1|^2 on the rfft bins: pre-emphasis applied in the frequency domain."""
    w = 2 * np.pi * np.fft.rfftfreq(n_fft, 1.0 / sample_rate) / sample_rate
    return np.abs(1 - 0.97 * np.exp(-1j * w)) ** 2


def _frame_power(
    padded: np.ndarray, geo: _FrameGeometry, first: int, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """(pre-emphasised power spectra (count, n_fft/2+1), level dBFS (count,)) of frames
    ``first..first+count-1`` of a signal left-padded by ``win/2``: frame k is
    ``padded[k*hop : k*hop+win]``, centred on time k*hop."""
    idx = (first + np.arange(count))[:, None] * geo.hop + np.arange(geo.win)[None, :]
    raw = padded[idx]
    power = np.abs(rfft(raw * np.hamming(geo.win)[None, :], n=geo.n_fft, axis=1)) ** 2
    power *= _emphasis(geo.sample_rate, geo.n_fft)[None, :]
    energy = 10 * np.log10(np.mean(np.square(raw), axis=1) + 1e-12)
    return power, energy


def _ceps(power: np.ndarray, geo: _FrameGeometry, warp: float) -> np.ndarray:
    mel = np.log(power @ _mel_bank(geo.sample_rate, geo.n_fft, warp).T + 1e-10)
    return dct(mel, type=2, norm="ortho", axis=1)[:, 1 : N_CEPS + 1]


def _frame_features(
    padded: np.ndarray, geo: _FrameGeometry, first: int, count: int, warp: float = 1.0
) -> np.ndarray:
    """(count, 13) level (dBFS RMS of the raw window) + c1..c12 (see :func:`_frame_power`)."""
    power, energy = _frame_power(padded, geo, first, count)
    return np.column_stack([energy, _ceps(power, geo, warp)])


def _stack(feats: np.ndarray, history: np.ndarray) -> np.ndarray:
    """Context stacking: each frame with the frames CONTEXT[j] earlier (``history`` holds the
    frames before ``feats``; zeros before the signal)."""
    depth = max(CONTEXT)
    full = np.vstack([history[-depth:] if depth else history[:0], feats])
    n = len(feats)
    parts = [full[depth - lag : depth - lag + n, 1:] for lag in CONTEXT]
    return np.column_stack([feats[:, :1], *parts])


# --------------------------------------------------------------------------- the model


@dataclass
class VisemeModel:
    """A small neural viseme classifier (see the module docstring).

    Input: the stacked cepstra of :func:`features` without the level column, (T, D) with
    D = 12 x len(CONTEXT); standardised by ``scale_mean``/``scale_sd``, less ``input_bias``
    (speaker calibration, :func:`calibrate`); one ReLU hidden layer (``hidden_w`` (D, H),
    ``hidden_b`` (H,)), a softmax output over ``classes`` (``out_w`` (H, C), ``out_b`` (C,)).
    ``class_means`` (C, D) are the training frames' mean features per class, kept for
    calibration.
    """

    classes: tuple[str, ...]
    scale_mean: np.ndarray  # (D,)
    scale_sd: np.ndarray  # (D,)
    hidden_w: np.ndarray  # (D, H)
    hidden_b: np.ndarray  # (H,)
    out_w: np.ndarray  # (H, C)
    out_b: np.ndarray  # (C,)
    class_means: np.ndarray  # (C, D)
    input_bias: np.ndarray | None = None  # (D,), feature units; None = zeros
    temperature: float = 1.5
    gate_db: tuple[float, float] = (-50.0, -30.0)
    smoothing_tau_s: float = 0.010
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.input_bias is None:
            self.input_bias = np.zeros(len(self.scale_mean))
        self._cols = np.array([VISEMES.index(c) for c in self.classes])

    @property
    def lag_s(self) -> float:
        """Delay of the weights relative to the frame times: the smoothing filter's group
        delay at low frequencies, hop * (1 - alpha) / alpha (the window is centred)."""
        if self.smoothing_tau_s <= 0:
            return 0.0
        alpha = 1.0 - np.exp(-HOP_S / self.smoothing_tau_s)
        return HOP_S * (1.0 - alpha) / alpha

    @property
    def latency_s(self) -> float:
        """Algorithmic latency of streaming: a frame needs audio up to half a window after its
        time, and its weights lag by :attr:`lag_s`."""
        return WINDOW_S / 2 + self.lag_s

    def logits(self, ceps: np.ndarray) -> np.ndarray:
        """(T, C) unnormalised log posteriors for stacked cepstra ``ceps`` (T, D)."""
        z = (ceps - self.input_bias - self.scale_mean) / self.scale_sd
        return np.maximum(z @ self.hidden_w + self.hidden_b, 0.0) @ self.out_w + self.out_b

    def posteriors(self, x: np.ndarray) -> np.ndarray:
        """(T, C) class posteriors (tempered) for stacked features x (T, 1 + D)."""
        logits = self.logits(x[:, 1:]) / self.temperature
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        return p / p.sum(axis=1, keepdims=True)

    def weights(self, x: np.ndarray) -> np.ndarray:
        """(T, 15) viseme weights before smoothing: posteriors scaled by the level gate."""
        post = self.posteriors(x)
        lo, hi = self.gate_db
        gate = np.clip((x[:, 0] - lo) / (hi - lo), 0.0, 1.0)
        out = np.zeros((len(x), len(VISEMES)))
        out[:, self._cols] = post * gate[:, None]
        sil = VISEMES.index("sil")
        out[:, sil] = 0
        out[:, sil] = 1 - out.sum(axis=1)
        return out

    # -- persistence
    _ARRAYS = (
        "scale_mean",
        "scale_sd",
        "hidden_w",
        "hidden_b",
        "out_w",
        "out_b",
        "class_means",
        "input_bias",
    )

    def to_json(self) -> dict:
        return {
            "format": MODEL_FORMAT,
            "classes": list(self.classes),
            **{name: np.round(getattr(self, name), 7).tolist() for name in self._ARRAYS},
            "temperature": self.temperature,
            "gate_db": list(self.gate_db),
            "smoothing_tau_s": self.smoothing_tau_s,
            "features": {
                "window_s": WINDOW_S,
                "hop_s": HOP_S,
                "n_mels": N_MELS,
                "n_ceps": N_CEPS,
                "context": list(CONTEXT),
                "mel_range_hz": list(MEL_RANGE_HZ),
            },
            "info": self.info,
        }

    @classmethod
    def from_json(cls, data: dict) -> VisemeModel:
        if data.get("format") != MODEL_FORMAT:
            raise VisemeError(
                f"not a facelab viseme model file of format {MODEL_FORMAT} "
                f"(found {data.get('format')!r}; retrain with python -m "
                "facelab.stimuli.viseme_training)"
            )
        return cls(
            classes=tuple(data["classes"]),
            **{name: np.asarray(data[name], dtype=float) for name in cls._ARRAYS},
            temperature=float(data["temperature"]),
            gate_db=tuple(data["gate_db"]),
            smoothing_tau_s=float(data["smoothing_tau_s"]),
            info=data.get("info", {}),
        )

    def save(self, path: Path | str) -> None:
        Path(path).write_text(json.dumps(self.to_json()) + "\n", encoding="utf-8")

    @classmethod
    def load(cls, path: Path | str) -> VisemeModel:
        try:
            return cls.from_json(json.loads(Path(path).read_text(encoding="utf-8")))
        except (OSError, json.JSONDecodeError, KeyError) as exc:
            raise VisemeError(f"{path}: cannot read the viseme model ({exc})") from None


@cache
def _default_model_cached() -> VisemeModel:
    if not MODEL_PATH.is_file():
        raise VisemeError(
            f"the shipped viseme model is missing: {MODEL_PATH} "
            "(python -m facelab.stimuli.viseme_training rebuilds it)"
        )
    return VisemeModel.load(MODEL_PATH)


def default_model() -> VisemeModel:
    """The shipped model (a copy; calibrate it freely)."""
    base = _default_model_cached()
    return replace(base, input_bias=base.input_bias.copy(), info=dict(base.info))


# --------------------------------------------------------------------------- analysis


class StreamingAnalyzer:
    """Feed audio chunks, get viseme frames as soon as their window is complete.

    ``latency_s`` is the algorithmic latency (window half + smoothing); in addition a frame
    waits for the chunk that completes its window (at most one hop, 10 ms, for chunks of
    10 ms or less). ``analyze`` is exactly this class fed the whole signal, then flushed.
    """

    def __init__(self, *, sample_rate: int, model: VisemeModel | None = None, warp: float = 1.0):
        self.model = model or default_model()
        self.geo = _FrameGeometry.for_rate(sample_rate)
        if not WARP_GRID[0] <= warp <= WARP_GRID[-1]:
            raise VisemeError(f"warp {warp} outside {WARP_GRID[0]}..{WARP_GRID[-1]}")
        self.warp = float(warp)
        self._buf = np.zeros(self.geo.win // 2, dtype=np.float64)  # left pad: frame 0 at t=0
        self._offset = 0  # samples dropped from the front of _buf
        self._next = 0  # next frame index
        self._history = np.zeros((max(CONTEXT), 1 + N_CEPS))
        alpha = (
            1.0 - np.exp(-HOP_S / self.model.smoothing_tau_s) if self.model.smoothing_tau_s else 1.0
        )
        self._smooth_b, self._smooth_a = [alpha], [1.0, alpha - 1.0]
        self._zi: np.ndarray | None = None
        self._n_in = 0

    @property
    def latency_s(self) -> float:
        return self.model.latency_s

    def feed(self, chunk: np.ndarray) -> VisemeTrack:
        chunk = np.asarray(chunk, dtype=np.float64).ravel()
        if chunk.size:
            self._buf = np.concatenate([self._buf, chunk])
            self._n_in += chunk.size
        return self._emit(limit=None)

    def flush(self) -> VisemeTrack:
        """Emit the remaining frames up to the end of the input (zero-padding the window)."""
        last_frame = (self._n_in - 1) // self.geo.hop if self._n_in else -1
        self._buf = np.concatenate([self._buf, np.zeros(self.geo.win)])
        return self._emit(limit=last_frame + 1)

    def _emit(self, limit: int | None) -> VisemeTrack:
        geo = self.geo
        available = (self._offset + len(self._buf) - geo.win) // geo.hop + 1
        stop = available if limit is None else min(available, limit)
        count = max(0, stop - self._next)
        if count == 0:
            return VisemeTrack(
                times=np.zeros(0),
                weights=np.zeros((0, len(VISEMES))),
                latency_s=self.model.lag_s,
                warp=self.warp,
            )
        # the buffer starts at a whole number of hops, so frame k is local frame k - offset/hop
        feats = _frame_features(
            self._buf, geo, self._next - self._offset // geo.hop, count, self.warp
        )
        stacked = _stack(feats, self._history)
        self._history = np.vstack([self._history, feats])[-max(CONTEXT) :]
        smooth = self._smooth(self.model.weights(stacked))
        times = (self._next + np.arange(count)) * HOP_S
        self._next += count
        drop = (self._next * geo.hop - self._offset) // geo.hop * geo.hop
        if drop > 0:  # samples before the next frame's window are no longer needed
            self._buf = self._buf[drop:]
            self._offset += drop
        return VisemeTrack(times=times, weights=smooth, latency_s=self.model.lag_s, warp=self.warp)

    def _smooth(self, raw: np.ndarray) -> np.ndarray:
        """One-pole low-pass per column, y[n] = y[n-1] + alpha (x[n] - y[n-1]), from silence."""
        if self._zi is None:
            start = np.zeros((1, len(VISEMES)))
            start[0, 0] = 1.0  # the output starts at rest (sil = 1)
            self._zi = -self._smooth_a[1] * start
        out, self._zi = signal.lfilter(self._smooth_b, self._smooth_a, raw, axis=0, zi=self._zi)
        return np.clip(out, 0.0, 1.0)


_ANALYSIS_RATE = 16_000  # what other rates are resampled to


def analysis_input(samples: np.ndarray, *, sample_rate: int) -> tuple[np.ndarray, int]:
    """(samples, rate) the analyser can frame: rates >= 16 kHz that are multiples of 100 Hz
    pass unchanged; any other rate >= 8 kHz (e.g. 11.025, 22.05, 44.1 kHz) is resampled to
    16 kHz (polyphase). Below 16 kHz the upper mel bands see no energy, so expect lower
    accuracy on 8-12 kHz telephone-band audio."""
    samples = np.asarray(samples)
    if samples.ndim != 1:
        raise VisemeError(f"expected mono samples of shape (n,), got shape {samples.shape}")
    if samples.size == 0:
        raise VisemeError("empty audio")
    if sample_rate < MIN_SAMPLE_RATE:
        raise VisemeError(
            f"sample rate {sample_rate} Hz is too low: the analyser needs >= {MIN_SAMPLE_RATE} Hz"
        )
    if sample_rate >= _ANALYSIS_RATE and sample_rate % 100 == 0:
        return samples, sample_rate
    out = resample(samples.astype(np.float32), rate_in=sample_rate, rate_out=_ANALYSIS_RATE)
    return out, _ANALYSIS_RATE


#: Mel-filter warps tried by :func:`choose_warp` (> 1: a shorter vocal tract than training).
WARP_GRID: tuple[float, ...] = tuple(round(0.72 + 0.04 * k, 2) for k in range(17))
WARP_SELECT_S = 8.0  # at most this much audio chooses the warp


def choose_warp(
    samples: np.ndarray, *, sample_rate: int, model: VisemeModel | None = None
) -> float:
    """Vocal-tract-length normalisation: the mel-filter warp (from :data:`WARP_GRID`, every
    other one first, then the best one's neighbours) under which the model is most confident
    about the utterance's loud frames - the mean log posterior of each frame's best class.
    One FFT pass over every third frame (the context frames of the stacked features) of at
    most ``WARP_SELECT_S`` of audio serves every warp."""
    from scipy.special import logsumexp

    model = model or default_model()
    samples, sample_rate = analysis_input(samples, sample_rate=sample_rate)
    x = np.asarray(samples[: int(WARP_SELECT_S * sample_rate)], dtype=np.float64)
    # warps whose filters would pass the Nyquist frequency cannot be judged at this rate
    grid = tuple(w for w in WARP_GRID if MEL_RANGE_HZ[1] * w < sample_rate / 2 - 100) or (1.0,)
    geo = _FrameGeometry.for_rate(sample_rate)
    stride = CONTEXT[1] - CONTEXT[0]
    if tuple(stride * k for k in range(len(CONTEXT))) != CONTEXT:
        stride = 1  # context lags not evenly spaced: every frame is needed
    # every stride-th frame only: its context frames are the strided frames before it
    sparse = replace(geo, hop=geo.hop * stride)
    padded = np.concatenate([np.zeros(geo.win // 2), x, np.zeros(geo.win)])
    count = (len(x) - 1) // sparse.hop + 1
    power, energy = _frame_power(padded, sparse, 0, count)  # one FFT pass for every warp
    loud = energy > model.gate_db[1] - 5
    if loud.sum() < 10:
        return 1.0  # too little speech to judge
    lags = [c // stride for c in CONTEXT]
    scores: dict[float, float] = {}

    def score(warp: float) -> float:
        if warp not in scores:
            ceps = _ceps(power, geo, warp)
            full = np.vstack([np.zeros((max(lags), ceps.shape[1])), ceps])
            stacked = np.column_stack(
                [full[max(lags) - lag : max(lags) - lag + len(ceps)] for lag in lags]
            )
            ll = model.logits(stacked[loud])
            scores[warp] = float((ll.max(axis=1) - logsumexp(ll, axis=1)).mean())
        return scores[warp]

    coarse = max(grid[::2], key=score)  # then its neighbours on the fine grid
    k = grid.index(coarse)
    return max(grid[max(0, k - 1) : k + 2], key=score)


def analyze(
    samples: np.ndarray,
    *,
    sample_rate: int,
    model: VisemeModel | None = None,
    warp: float | str = 1.0,
) -> VisemeTrack:
    """15 viseme weights per 10 ms frame from audio alone (see the module docstring).

    samples : (n,) mono float in [-1, 1]; sample_rate : Hz, any rate >= 8 kHz
    (:func:`analysis_input` resamples rates the framing cannot use).
    warp : mel-filter warp, 1 (default) = the filters the model was trained with (the model
    is trained across voices and warps, see the module docstring); ``"auto"`` chooses one
    per utterance by :func:`choose_warp` (a calibrated model always runs at warp 1). The
    track's ``warp`` says which was used.
    Returns frames at t = 0, 0.01, … up to the last sample; each frame's window is centred
    on its time, and ``latency_s`` is the smoothing lag (``compensated()`` removes it).
    """
    samples, sample_rate = analysis_input(samples, sample_rate=sample_rate)
    model = model or default_model()
    if warp == "auto":
        warp = (
            1.0
            if "calibrated" in model.info
            else choose_warp(samples, sample_rate=sample_rate, model=model)
        )
    elif isinstance(warp, str):
        raise VisemeError(f"warp {warp!r}: use 'auto' or a number")
    stream = StreamingAnalyzer(sample_rate=sample_rate, model=model, warp=float(warp))
    head, tail = stream.feed(samples), stream.flush()
    return VisemeTrack(
        times=np.concatenate([head.times, tail.times]),
        weights=np.vstack([head.weights, tail.weights]),
        latency_s=stream.model.lag_s,
        warp=stream.warp,
    )


def features(
    samples: np.ndarray, *, sample_rate: int, warp: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """(times (T,), stacked features (T, D)) exactly as the analyser sees them (training);
    ``warp`` scales the mel filters' frequencies (:func:`choose_warp`)."""
    samples, sample_rate = analysis_input(samples, sample_rate=sample_rate)
    geo = _FrameGeometry.for_rate(sample_rate)
    x = np.asarray(samples, dtype=np.float64)
    padded = np.concatenate([np.zeros(geo.win // 2), x, np.zeros(geo.win)])
    count = (len(x) - 1) // geo.hop + 1
    feats = _frame_features(padded, geo, 0, count, warp)
    return np.arange(count) * HOP_S, _stack(feats, np.zeros((max(CONTEXT), feats.shape[1])))


# --------------------------------------------------------------------------- alignment

#: A stretch of speech longer than this that only one side has is a text/audio mismatch.
MISMATCH_S = 0.6
#: The largest local speaking-rate ratio between the recording and the TTS reference.
MAX_SLOPE = 3.5


@dataclass(frozen=True)
class Alignment:
    """Phones of ``text`` timed on a recording (:func:`align_phones`): ``phones`` (Phone, s),
    ``words`` and ``accents`` of the front end moved onto the recording's time, the DTW
    ``mean_cost`` and the reference (TTS) duration."""

    phones: tuple
    words: tuple
    accents: tuple
    mean_cost: float
    reference_s: float


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


def align_phones(
    samples: np.ndarray, *, sample_rate: int, text: str, model: VisemeModel | None = None
) -> Alignment:
    """Time the phonemes of ``text`` on a recording of it.

    The text is synthesised by OpenJTalk (its phone timeline known exactly); both signals
    are turned into posteriorgrams - the analyser's log posteriors of the 13 viseme classes
    per frame (floored at ``POSTERIOR_FLOOR``), plus the frame level relative to the
    utterance's loud level - which are speaker-independent as far as the analyser is, and
    aligned by DTW (:func:`facelab.stimuli.dtw.dtw_path`); each reference phone boundary
    moves along the path onto the recording. (Cepstra normalised per utterance, the first
    version, kept too much of the speaker: on eSpeak voices 0.44-0.83 of vowel frames.)
    Where one side holds more than ``MISMATCH_S`` of speech that the other lacks (a long
    horizontal or vertical run of the path over loud frames), the text and the audio
    disagree and :class:`VisemeError` says where."""
    from facelab.stimuli.dtw import dtw_path
    from facelab.stimuli.speech import Phone, synthesize

    samples, rate = analysis_input(samples, sample_rate=sample_rate)
    ref = synthesize(text, sample_rate=rate)
    model = model or default_model()
    _, xa = features(samples, sample_rate=rate)
    _, xr = features(ref.samples, sample_rate=rate)
    level_a = _frame_level(samples, rate, len(xa))
    level_r = _frame_level(ref.samples, rate, len(xr))
    loud_a = level_a > np.percentile(level_a, 95) - 25
    loud_r = level_r > np.percentile(level_r, 95) - 25
    # leading and trailing silence stay out of the DTW (their lengths are arbitrary): the
    # speech spans are aligned, the silences before and after map linearly
    ra, rb = _speech_span(loud_r)
    aa, ab = _speech_span(loud_a)
    path, mean_cost = dtw_path(_posteriorgram(xr, model)[ra:rb], _posteriorgram(xa, model)[aa:ab])
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
    return Alignment(phones, words, accents, mean_cost, ref.duration_s)


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


# --------------------------------------------------------------------------- calibration


def vowel_segments(
    track: VisemeTrack,
    *,
    min_s: float = 0.06,
    merge_gap_s: float = 0.08,
    threshold: float = 0.5,
    widen: bool = False,
) -> list[tuple[int, int]]:
    """Voiced stretches as frame index ranges [start, stop): where 1 - sil >= threshold,
    gaps shorter than ``merge_gap_s`` merged, pieces shorter than ``min_s`` dropped; with
    ``widen``, each grown over its rising and falling edges (as vowel isolation uses them)."""
    active = (1.0 - track.weights[:, 0]) >= threshold
    fps = track.fps
    segs: list[list[int]] = []
    for i, on in enumerate(active):
        if not on:
            continue
        if segs and i - segs[-1][1] <= merge_gap_s * fps:
            segs[-1][1] = i + 1
        else:
            segs.append([i, i + 1])
    kept = [(a, b) for a, b in segs if (b - a) >= min_s * fps]
    return _widen(track, kept) if widen else kept


def calibrate(
    model: VisemeModel,
    samples: np.ndarray,
    *,
    sample_rate: int,
    vowels: str = "aiueo",
    prior_frames: float = 20.0,
    steps: int = 60,
) -> VisemeModel:
    """Adapt ``model`` to a speaker from a recording of the vowels spoken in ``vowels`` order
    with pauses between them (e.g. あ、い、う、え、お).

    Vowel segments are found with the model's own voicing decision, their middle 60 % frames
    are used:

    1. an input bias (feature units) moves the speaker's vowels onto the training vowels: the
       mean over vowels of (segment mean - class mean), each shrunk by n / (n + prior_frames);
    2. the output layer is then fitted to those frames by ``steps`` of gradient descent on the
       cross-entropy plus a penalty pulling it back to the shipped weights (strength
       ``prior_frames`` frames' worth), so a handful of frames moves it only as far as they
       justify;
    3. the level gate is set from the vowel level (peak 2 dB below its 90th percentile).

    The calibrated model runs at warp 1 (the calibration replaces the warp search).
    """
    track = analyze(samples, sample_rate=sample_rate, model=model, warp=1.0)
    segs = vowel_segments(track)
    if len(segs) != len(vowels):
        raise VisemeError(
            f"calibration recording: found {len(segs)} voiced segments, expected "
            f"{len(vowels)} ({vowels}); leave clear pauses between the vowels"
        )
    _, x = features(samples, sample_rate=sample_rate)
    cores, labels, shifts = [], [], []
    for (a, b), vowel in zip(segs, vowels, strict=True):
        n = b - a
        core = x[a + int(0.2 * n) : b - int(0.2 * n), 1:]
        c = model.classes.index(VOWEL_VISEMES[VOWELS.index(vowel)])
        shifts.append(
            (core.mean(axis=0) - model.class_means[c]) * len(core) / (len(core) + prior_frames)
        )
        cores.append(core)
        labels += [c] * len(core)
    tuned = replace(model, input_bias=np.mean(shifts, axis=0))
    feats, target = np.vstack(cores), np.array(labels)
    z = (feats - tuned.input_bias - tuned.scale_mean) / tuned.scale_sd
    hidden = np.maximum(z @ tuned.hidden_w + tuned.hidden_b, 0.0)
    w0, b0 = tuned.out_w, tuned.out_b
    w, b = w0.copy(), b0.copy()
    onehot = np.eye(len(model.classes))[target]
    strength = prior_frames / len(feats)
    rate = 0.5 / max(float(np.mean(np.sum(hidden**2, axis=1))), 1e-9)
    for _ in range(steps):
        logits = hidden @ w + b
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        p /= p.sum(axis=1, keepdims=True)
        grad = (p - onehot) / len(feats)
        w -= rate * (hidden.T @ grad + strength * (w - w0))
        b -= rate * (grad.sum(axis=0) + strength * (b - b0))
    levels = np.concatenate([x[a:b_, 0] for a, b_ in segs])
    top = float(np.percentile(levels, 90)) - 2.0
    info = {
        **model.info,
        "calibrated": {"vowels": vowels, "segments_s": [[a * HOP_S, e * HOP_S] for a, e in segs]},
    }
    return replace(tuned, out_w=w, out_b=b, gate_db=(top - 20.0, top), info=info)


# --------------------------------------------------------------------------- vowel isolation


def _widen(
    track: VisemeTrack, segs: list[tuple[int, int]], *, floor: float = 0.02
) -> list[tuple[int, int]]:
    """Grow each segment over its rising and falling edges (while 1 - sil > ``floor``),
    never into a neighbour."""
    active = (1.0 - track.weights[:, 0]) > floor
    out: list[tuple[int, int]] = []
    for i, (a, b) in enumerate(segs):
        lo = out[-1][1] if out else 0
        hi = segs[i + 1][0] if i + 1 < len(segs) else len(active)
        while a > lo and active[a - 1]:
            a -= 1
        while b < hi and active[b]:
            b += 1
        out.append((a, b))
    return out


def isolate_vowels(
    track: VisemeTrack, *, vowels: str, segments: Iterable[tuple[int, int]] | None = None
) -> VisemeTrack:
    """Keep only the intended vowel per vowel segment (seed figure 7).

    In the i-th voiced segment the vowel ``vowels[i]`` keeps its intensity and the other four
    vowel columns are set to 0; consonant columns are left alone; ``sil`` takes the rest.
    Segments are found from the track (:func:`vowel_segments`, widened) unless given.
    """
    segs = list(segments) if segments is not None else vowel_segments(track, widen=True)
    if len(segs) != len(vowels):
        raise VisemeError(
            f"vowel isolation: found {len(segs)} voiced segments but expected_vowels "
            f"is {vowels!r} ({len(vowels)}); check the recording or the text"
        )
    weights = track.weights.copy()
    for (a, b), vowel in zip(segs, vowels, strict=True):
        keep = VISEMES.index(VOWEL_VISEMES[VOWELS.index(vowel)])
        for col in _VOWEL_INDEX:
            if col != keep:
                weights[a:b, col] = 0.0
    weights[:, 0] = 0.0
    weights[:, 0] = np.clip(1.0 - weights.sum(axis=1), 0.0, 1.0)
    return replace(track, weights=weights)
