"""The audio-only 15-viseme analyser: a small network over cepstral features, offline and
streaming.

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

Speaker independence comes from the training data and from a causal cepstral mean
normalisation. Training: two synthesizers with exact phoneme times (OpenJTalk's statistical
mei voice in 14 settings of speed, pitch and all-pass constant, and eSpeak NG's formant voices
in 29 variants at random rates and pitches) and three natural-sounding neural voices (Kokoro,
vowel cores timed by alignment), every utterance also entered at a random mel-filter warp of
0.8..1.25 (vocal-tract-length augmentation) - see ``stimuli/speech/training.py``. The
normalisation (:class:`~facelab.stimuli.speech.features.MeanNormalisation`, kept in the model
file) subtracts from each frame's cepstra the running mean of the loud frames so far (time
constant 2 s, starting from the training speech's mean): the speaker's and the channel's
average spectral shape fades out as the utterance goes on, with no look-ahead. Trained on the
synthesizers and two of the natural voices, the network read the third one's sentences at
0.62-0.90 without it and 0.84-0.91 with it (each voice left out in turn).
:func:`analyze` then chooses a mel-filter warp per utterance (:func:`choose_warp`,
vocal-tract-length normalisation by the model's confidence; ``warp=1`` turns it off). Chosen as
the default on material that may be tuned on only - the natural training voices each left out
of a model trained without it, as recorded and read at 0.85 / 0.75 of their rate (a lower,
longer vocal tract), and synthetic voices kept out of training: mean 0.877 / 0.872 / 0.866
against 0.879 / 0.836 / 0.727 at warp 1, synthetic 0.950 against 0.936; the search finds the
simulated shift (median warp 0.74-0.76 at rate 0.75). ``facelab bench visemes`` reports both.

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
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path

import numpy as np
from scipy import signal

from facelab.errors import VisemeError
from facelab.resources import package_file
from facelab.stimuli.speech.audio import MIN_SAMPLE_RATE, frame_chunks, resample
from facelab.stimuli.speech.features import (
    CONTEXT,
    HOP_S,
    MEL_RANGE_HZ,
    N_CEPS,
    N_MELS,
    WINDOW_S,
    FrameGeometry,
    MeanNormalisation,
    cepstra,
    frame_features,
    frame_power,
    stack_context,
    utterance_features,
)
from facelab.stimuli.speech.track import VISEMES, VisemeTrack

MODEL_PATH = package_file("facelab.stimuli", "data", "viseme_model.json")
MODEL_FORMAT = "facelab-viseme-mlp-1"

__all__ = [
    "StreamingAnalyzer",
    "VisemeModel",
    "WarpAdaptingAnalyzer",
    "analyze",
    "analyze_streamed",
    "choose_warp",
    "default_model",
    "features",
    "raw_features",
]

# --------------------------------------------------------------------------- the model


@dataclass
class VisemeModel:
    """A small neural viseme classifier (see the module docstring).

    Input: the stacked cepstra of :func:`features` without the level column, (T, D) with
    D = 12 x len(CONTEXT); standardised by ``scale_mean``/``scale_sd``, less ``input_bias``
    (speaker calibration, :func:`calibrate`); one ReLU hidden layer (``hidden_w`` (D, H),
    ``hidden_b`` (H,)), a softmax output over ``classes`` (``out_w`` (H, C), ``out_b`` (C,)).
    ``class_means`` (C, D) are the training frames' mean features per class, kept for
    calibration. ``normalisation``: the causal cepstral mean normalisation the model was
    trained with (None: none, as models before it).
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
    normalisation: MeanNormalisation | None = None

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
            **(
                {"mean_normalisation": self.normalisation.to_json()}
                if self.normalisation is not None
                else {}
            ),
            "info": self.info,
        }

    @classmethod
    def from_json(cls, data: dict) -> VisemeModel:
        if data.get("format") != MODEL_FORMAT:
            raise VisemeError(
                f"not a facelab viseme model file of format {MODEL_FORMAT} "
                f"(found {data.get('format')!r}; retrain with python -m "
                "facelab.stimuli.speech.training)"
            )
        return cls(
            classes=tuple(data["classes"]),
            **{name: np.asarray(data[name], dtype=float) for name in cls._ARRAYS},
            temperature=float(data["temperature"]),
            gate_db=tuple(data["gate_db"]),
            smoothing_tau_s=float(data["smoothing_tau_s"]),
            info=data.get("info", {}),
            normalisation=(
                MeanNormalisation.from_json(data["mean_normalisation"])
                if "mean_normalisation" in data
                else None
            ),
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
            "(python -m facelab.stimuli.speech.training rebuilds it)"
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
        self.geo = FrameGeometry.for_rate(sample_rate)
        if not WARP_GRID[0] <= warp <= WARP_GRID[-1]:
            raise VisemeError(f"warp {warp} outside {WARP_GRID[0]}..{WARP_GRID[-1]}")
        self.warp = float(warp)
        self._buf = np.zeros(self.geo.win // 2, dtype=np.float64)  # left pad: frame 0 at t=0
        self._offset = 0  # samples dropped from the front of _buf
        self._next = 0  # next frame index
        self._history = np.zeros((max(CONTEXT), 1 + N_CEPS))
        self._norm_state = None
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
        feats = frame_features(
            self._buf, geo, self._next - self._offset // geo.hop, count, self.warp
        )
        if self.model.normalisation is not None:
            feats, self._norm_state = self.model.normalisation.apply(feats, self._norm_state)
        stacked = stack_context(feats, self._history)
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


class WarpAdaptingAnalyzer:
    """:class:`StreamingAnalyzer` whose mel-filter warp follows the talker (the live path's
    vocal-tract-length normalisation): every :attr:`RECHOOSE_S` of audio, until
    :data:`WARP_SELECT_S` have been heard, :func:`choose_warp` judges the audio so far - the
    offline criterion, applied causally. When it picks another warp, a new analyser at that
    warp is fed the audio so far again (no frame is emitted twice: the next frame continues
    the sequence), so from then on the frames are the offline analysis at the chosen warp.
    Starts at ``warp`` (1, or what an earlier turn of the same talker settled on) and keeps
    it until there is speech enough to judge (leading silence changes nothing).
    ``warps``: (sample index, warp) of each change. A calibrated model runs at warp 1, as in
    :func:`analyze`.
    """

    RECHOOSE_S = 0.5

    def __init__(
        self, *, sample_rate: int, model: VisemeModel | None = None, warp: float = 1.0
    ) -> None:
        self.model = model or default_model()
        self.sample_rate = sample_rate
        self._fixed = "calibrated" in self.model.info  # a calibrated model runs at warp 1
        self.stream = StreamingAnalyzer(sample_rate=sample_rate, model=self.model,
                                        warp=1.0 if self._fixed else warp)  # fmt: skip
        self._heard: list[np.ndarray] = []  # the audio so far, until the warp is settled
        self._n_heard = 0
        self._next_choice = round(self.RECHOOSE_S * sample_rate)
        self._emitted = 0  # frames handed out
        self.warps: list[tuple[int, float]] = [(0, self.stream.warp)]

    @property
    def warp(self) -> float:
        return self.stream.warp

    @property
    def latency_s(self) -> float:
        return self.stream.latency_s

    def feed(self, chunk: np.ndarray) -> VisemeTrack:
        chunk = np.asarray(chunk, dtype=np.float64).ravel()
        if not self._fixed:
            self._heard.append(chunk)
        self._n_heard += chunk.size
        out = self.stream.feed(chunk)
        if not self._fixed and self._n_heard >= self._next_choice:
            self._next_choice += round(self.RECHOOSE_S * self.sample_rate)
            heard = np.concatenate(self._heard)
            self._heard = [heard]
            limit = round(WARP_SELECT_S * self.sample_rate)
            warp = choose_warp(heard[:limit], sample_rate=self.sample_rate, model=self.model,
                               undecided=None)  # too little speech yet: keep the warp
            if warp is not None and warp != self.stream.warp:
                # a new analyser at the chosen warp, fed the audio so far: it has as many
                # frames ready as the old one; those not yet handed out, and all later
                # frames, come from it
                self.stream = StreamingAnalyzer(sample_rate=self.sample_rate, model=self.model,
                                                warp=warp)  # fmt: skip
                replay = self.stream.feed(heard)
                done = self._emitted
                out = VisemeTrack(times=replay.times[done:], weights=replay.weights[done:],
                                  latency_s=replay.latency_s, warp=warp)  # fmt: skip
                self.warps.append((self._n_heard, warp))
            if self._n_heard >= limit:  # the warp is settled
                self._heard = []
                self._fixed = True
        self._emitted += len(out.times)
        return out

    def flush(self) -> VisemeTrack:
        out = self.stream.flush()
        self._emitted += len(out.times)
        return out


_ANALYSIS_RATE = 16_000  # what other rates are resampled to


def analyze_streamed(
    samples: np.ndarray, *, sample_rate: int, model: VisemeModel | None = None
) -> VisemeTrack:
    """What the live path hears: ``samples`` fed in 10 ms chunks to a
    :class:`WarpAdaptingAnalyzer` (the warp found as the audio comes), then flushed; the
    smoothing lag removed as :func:`analyze`'s tracks are by ``compensated()``. For
    measuring the live analysis offline (``facelab bench visemes``)."""
    samples, sample_rate = analysis_input(samples, sample_rate=sample_rate)
    stream = WarpAdaptingAnalyzer(sample_rate=sample_rate, model=model)
    hop = round(HOP_S * sample_rate)
    x = np.asarray(samples, dtype=np.float64)
    parts = [stream.feed(x[k : k + hop]) for k in range(0, len(x), hop)]
    return _whole_track([*parts, stream.flush()], stream).compensated()


def _whole_track(
    parts: list[VisemeTrack], stream: StreamingAnalyzer | WarpAdaptingAnalyzer
) -> VisemeTrack:
    """The tracks a stream emitted, one after the other, as one (its lag and final warp)."""
    return VisemeTrack(
        times=np.concatenate([p.times for p in parts]),
        weights=np.vstack([p.weights for p in parts]),
        latency_s=stream.model.lag_s,
        warp=stream.warp,
    )


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
    samples: np.ndarray,
    *,
    sample_rate: int,
    model: VisemeModel | None = None,
    undecided: float | None = 1.0,
) -> float | None:
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
    geo = FrameGeometry.for_rate(sample_rate)
    stride = CONTEXT[1] - CONTEXT[0]
    if tuple(stride * k for k in range(len(CONTEXT))) != CONTEXT:
        stride = 1  # context lags not evenly spaced: every frame is needed
    # every stride-th frame only: its context frames are the strided frames before it
    sparse = replace(geo, hop=geo.hop * stride)
    padded = np.concatenate([np.zeros(geo.win // 2), x, np.zeros(geo.win)])
    count = (len(x) - 1) // sparse.hop + 1
    power, energy = frame_power(padded, sparse, 0, count)  # one FFT pass for every warp
    loud = energy > model.gate_db[1] - 5
    if loud.sum() < 10:
        return undecided  # too little speech to judge
    lags = [c // stride for c in CONTEXT]
    scores: dict[float, float] = {}

    def score(warp: float) -> float:
        if warp not in scores:
            ceps = cepstra(power, geo, warp)
            if model.normalisation is not None:
                hop_s = sparse.hop / sample_rate
                ceps = model.normalisation.apply(np.column_stack([energy, ceps]), hop_s=hop_s)[0]
                ceps = ceps[:, 1:]
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
    warp: float | str = "auto",
) -> VisemeTrack:
    """15 viseme weights per 10 ms frame from audio alone (see the module docstring).

    samples : (n,) mono float in [-1, 1]; sample_rate : Hz, any rate >= 8 kHz
    (:func:`analysis_input` resamples rates the framing cannot use).
    warp : ``"auto"`` (default) chooses the mel-filter warp per utterance by
    :func:`choose_warp` (vocal-tract-length normalisation; a calibrated model always runs at
    warp 1); a number fixes it, 1 = the filters the model was trained with. The track's
    ``warp`` says which was used. (Live audio: :class:`StreamingAnalyzer` runs at a given
    warp; :class:`WarpAdaptingAnalyzer` chooses it as it streams, as this does.)
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
    return _whole_track([stream.feed(samples), stream.flush()], stream)


def raw_features(
    samples: np.ndarray, *, sample_rate: int, warp: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """(times (T,), level + c1..c12 (T, 1 + N_CEPS)) of every frame, before normalisation and
    stacking; ``warp`` scales the mel filters' frequencies (:func:`choose_warp`)."""
    samples, sample_rate = analysis_input(samples, sample_rate=sample_rate)
    geo = FrameGeometry.for_rate(sample_rate)
    x = np.asarray(samples, dtype=np.float64)
    padded = np.concatenate([np.zeros(geo.win // 2), x, np.zeros(geo.win)])
    count = (len(x) - 1) // geo.hop + 1
    # frame by frame, in chunks of 1,000-2,000 frames: the windows and spectra of a 5-minute
    # recording at once took about 2 GB; the features are the same but for the last bit of
    # some (matrix products round by how many rows they have)
    feats = [frame_features(padded, geo, a, b - a, warp)
             for a, b in frame_chunks(count, at_most=2000)]  # fmt: skip
    return np.arange(count) * HOP_S, np.vstack(feats)


def features(
    samples: np.ndarray,
    *,
    sample_rate: int,
    warp: float = 1.0,
    normalisation: MeanNormalisation | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(times (T,), stacked features (T, 1 + D)) exactly as a model with this
    ``normalisation`` sees them (pass ``model.normalisation``); ``warp`` scales the mel
    filters' frequencies (:func:`choose_warp`)."""
    times, feats = raw_features(samples, sample_rate=sample_rate, warp=warp)
    return times, utterance_features(feats, normalisation=normalisation)
