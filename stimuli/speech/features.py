"""Acoustic features of the viseme analyser: log-mel cepstra with causal context.

Per 10 ms frame: a 32 ms Hamming window centred on the frame time, pre-emphasis (0.97,
applied to the spectrum), a mel filterbank (40 bands, 60-7600 Hz, at the input's own rate,
optionally warped for vocal-tract-length normalisation), log, DCT -> 12 cepstral coefficients
plus the log energy, stacked with the frames 30 ms and 60 ms earlier. A model may also
subtract a causal running mean of the cepstra (:class:`MeanNormalisation`: the speaker's and
channel's average spectral shape), before stacking.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np
from scipy.fft import dct, rfft
from scipy.signal import lfilter

from facelab.errors import VisemeError

__all__ = [
    "MeanNormalisation",
    "utterance_features",
]

# --------------------------------------------------------------------------- features

WINDOW_S = 0.032
HOP_S = 0.010
N_MELS = 40
N_CEPS = 12
CONTEXT = (0, 3, 6)  # frames back
MEL_RANGE_HZ = (60.0, 7600.0)


@cache
def mel_bank(sample_rate: int, n_fft: int, warp: float = 1.0) -> np.ndarray:
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
class FrameGeometry:
    sample_rate: int
    win: int
    hop: int
    n_fft: int

    @classmethod
    def for_rate(cls, sample_rate: int) -> FrameGeometry:
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
def emphasis(sample_rate: int, n_fft: int) -> np.ndarray:
    """|1 - 0.97 z^-1|^2 on the rfft bins: pre-emphasis applied in the frequency domain."""
    w = 2 * np.pi * np.fft.rfftfreq(n_fft, 1.0 / sample_rate) / sample_rate
    return np.abs(1 - 0.97 * np.exp(-1j * w)) ** 2


def frame_power(
    padded: np.ndarray, geo: FrameGeometry, first: int, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """(pre-emphasised power spectra (count, n_fft/2+1), level dBFS (count,)) of frames
    ``first..first+count-1`` of a signal left-padded by ``win/2``: frame k is
    ``padded[k*hop : k*hop+win]``, centred on time k*hop."""
    idx = (first + np.arange(count))[:, None] * geo.hop + np.arange(geo.win)[None, :]
    raw = padded[idx]
    power = np.abs(rfft(raw * np.hamming(geo.win)[None, :], n=geo.n_fft, axis=1)) ** 2
    power *= emphasis(geo.sample_rate, geo.n_fft)[None, :]
    energy = 10 * np.log10(np.mean(np.square(raw), axis=1) + 1e-12)
    return power, energy


def cepstra(power: np.ndarray, geo: FrameGeometry, warp: float) -> np.ndarray:
    mel = np.log(power @ mel_bank(geo.sample_rate, geo.n_fft, warp).T + 1e-10)
    return dct(mel, type=2, norm="ortho", axis=1)[:, 1 : N_CEPS + 1]


def frame_features(
    padded: np.ndarray, geo: FrameGeometry, first: int, count: int, warp: float = 1.0
) -> np.ndarray:
    """(count, 13) level (dBFS RMS of the raw window) + c1..c12 (see :func:`frame_power`)."""
    power, energy = frame_power(padded, geo, first, count)
    return np.column_stack([energy, cepstra(power, geo, warp)])


def stack_context(feats: np.ndarray, history: np.ndarray) -> np.ndarray:
    """Context stacking: each frame with the frames CONTEXT[j] earlier (``history`` holds the
    frames before ``feats``; zeros before the signal)."""
    depth = max(CONTEXT)
    full = np.vstack([history[-depth:] if depth else history[:0], feats])
    n = len(feats)
    parts = [full[depth - lag : depth - lag + n, 1:] for lag in CONTEXT]
    return np.column_stack([feats[:, :1], *parts])


@dataclass(frozen=True)
class MeanNormalisation:
    """Causal cepstral mean normalisation: each frame's c1..c12 less the running mean of the
    loud frames' cepstra so far (the speaker's and the channel's average spectral shape),
    forgotten with time constant ``tau_s``, starting from ``prior`` (N_CEPS,) - the training
    speech's mean - worth ``prior_s`` of speech. Frames count as loud above ``gate_db`` dBFS.
    Needs no audio after the frame, so streaming latency is unchanged."""

    prior: np.ndarray = field(repr=False)  # (N_CEPS,)
    tau_s: float = 2.0
    prior_s: float = 0.5
    gate_db: float = -40.0

    def start(self) -> tuple[np.ndarray, float]:
        """The state before any audio: (weighted sum of cepstra (N_CEPS,), weight (frames))."""
        weight = self.prior_s / HOP_S
        return np.asarray(self.prior, float) * weight, weight

    def apply(
        self,
        feats: np.ndarray,
        state: tuple[np.ndarray, float] | None = None,
        *,
        hop_s: float = HOP_S,
    ) -> tuple[np.ndarray, tuple[np.ndarray, float]]:
        """(normalised feats (T, 1 + N_CEPS), state after them) for consecutive frames
        ``feats`` (level, c1..c12) ``hop_s`` apart; ``state`` from :meth:`start` or the
        previous call."""
        total, weight = self.start() if state is None else state
        if len(feats) == 0:
            return feats, (total, weight)
        keep = np.exp(-hop_s / self.tau_s)
        loud = (feats[:, 0] > self.gate_db).astype(float)
        # s[t] = keep s[t-1] + loud[t] c[t]; w[t] = keep w[t-1] + loud[t] (scaled to 10 ms)
        gain = loud * hop_s / HOP_S
        sums, zs = lfilter(
            [1.0],
            [1.0, -keep],
            gain[:, None] * feats[:, 1:],
            axis=0,
            zi=keep * np.asarray(total)[None, :],
        )
        weights, zw = lfilter([1.0], [1.0, -keep], gain, zi=[keep * weight])
        out = feats.copy()
        out[:, 1:] -= sums / weights[:, None]
        return out, (zs[0] / keep, float(zw[0]) / keep)

    def to_json(self) -> dict:
        return {
            "prior": np.round(np.asarray(self.prior, float), 7).tolist(),
            "tau_s": self.tau_s,
            "prior_s": self.prior_s,
            "gate_db": self.gate_db,
        }

    @classmethod
    def from_json(cls, data: dict) -> MeanNormalisation:
        return cls(
            prior=np.asarray(data["prior"], float),
            tau_s=float(data["tau_s"]),
            prior_s=float(data["prior_s"]),
            gate_db=float(data["gate_db"]),
        )


def utterance_features(
    feats: np.ndarray, *, normalisation: MeanNormalisation | None = None
) -> np.ndarray:
    """(T, 1 + D) stacked features of a whole utterance's frames ``feats`` (level + c1..c12,
    (T, 1 + N_CEPS)), normalised from its start when ``normalisation`` is given and stacked
    with silence before it - what the streaming analyser computes frame by frame."""
    if normalisation is not None:
        feats = normalisation.apply(feats)[0]
    return stack_context(feats, np.zeros((max(CONTEXT), feats.shape[1])))
