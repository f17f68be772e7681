"""Speech in noise: speech-shaped noise, levels in dB and mixing at a signal-to-noise ratio.
Pure numpy/scipy; the noise file is read by the caller.

* :func:`active_level_db` - the speech's active level: the RMS (dBFS) of its 20 ms frames
  within 40 dB of the loudest frame (pauses and padding left out; a simple stand-in for ITU-T
  P.56's active speech level);
* :func:`long_term_spectrum` - the long-term average magnitude spectrum of a set of signals
  (Welch, Hann windows of 1024 samples, half overlapping), the "speech-shaped" of
  speech-shaped noise;
* :func:`shaped_noise` - Gaussian noise with that spectrum (complex Gaussian bins);
* :func:`mix_at_snr` - the speech scaled to a fixed active level and the noise's RMS
  (between its fades) set ``snr_db`` below it, faded in and out at the clip's ends; what
  was mixed is returned as a :class:`MixRecord` (written beside each clip).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

__all__ = [
    "NOISE_SYNTHESIS",
    "MixRecord",
    "active_level_db",
    "long_term_spectrum",
    "mix_at_snr",
    "noise_rng",
    "rms_db",
    "shaped_noise",
]

_FLOOR = 1e-12
FRAME_S = 0.020
ACTIVE_RANGE_DB = 40.0
NPERSEG = 1024


def rms_db(x: np.ndarray) -> float:
    """RMS level in dBFS (1.0 = 0 dBFS)."""
    x = np.asarray(x, dtype=np.float64)
    return float(10.0 * np.log10(max(float(np.mean(x**2)) if len(x) else 0.0, _FLOOR)))


def active_level_db(x: np.ndarray, *, sample_rate: int) -> float:
    """The RMS (dBFS) of the 20 ms frames of ``x`` within 40 dB of its loudest frame."""
    x = np.asarray(x, dtype=np.float64)
    n = max(1, round(FRAME_S * sample_rate))
    frames = x[: len(x) // n * n].reshape(-1, n)
    if len(frames) == 0:
        return rms_db(x)
    power = np.mean(frames**2, axis=1)
    top = power.max()
    if top <= _FLOOR:
        return rms_db(x)
    active = power[power >= top * 10 ** (-ACTIVE_RANGE_DB / 10)]
    return float(10.0 * np.log10(max(float(active.mean()), _FLOOR)))


def long_term_spectrum(signals: Sequence[np.ndarray], *, sample_rate: int) -> np.ndarray:
    """(NPERSEG // 2 + 1,) the long-term average magnitude spectrum of ``signals`` (their
    Welch power spectra averaged, weighted by length), square-rooted."""
    from scipy import signal  # on first use: scipy.signal takes ~1.5 s to import

    total, weight = None, 0
    for x in signals:
        x = np.asarray(x, dtype=np.float64)
        if len(x) < NPERSEG:
            x = np.pad(x, (0, NPERSEG - len(x)))
        _, p = signal.welch(x, fs=sample_rate, nperseg=NPERSEG)
        total = p * len(x) if total is None else total + p * len(x)
        weight += len(x)
    if total is None:
        raise ValueError("no signal to take a spectrum of")
    return np.sqrt(total / weight)


def noise_rng(*parts: str) -> np.random.Generator:
    """A generator seeded from ``parts`` (e.g. the stimulus set, stimulus and SNR): the same
    noise token on every machine."""
    digest = hashlib.sha256("/".join(parts).encode("utf-8")).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


#: how :func:`shaped_noise` makes its numbers (part of a noise clip's spec hash, so clips made
#: the earlier way are rendered again). 1: random phases and Rayleigh magnitudes at the clip's
#: own length; 2: complex Gaussian bins at the next length with small prime factors, cut to
#: the clip (the same distribution; a prime length's inverse FFT cost ~6 times as much)
NOISE_SYNTHESIS = 2


def shaped_noise(spectrum: np.ndarray, *, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) Gaussian noise whose magnitude spectrum follows ``spectrum`` (Welch bins of
    :data:`NPERSEG`), RMS 1.

    Each frequency bin of a longer token (the next length of at least ``max(n, NPERSEG)``
    whose only prime factors are small) is ``shape x (a + ib)``, a and b standard normal
    from ``rng`` - a uniform phase and a Rayleigh magnitude, as random-phase synthesis with
    Rayleigh amplitudes draws them - and the inverse FFT's first ``n`` samples are the noise:
    a stretch of a stationary Gaussian process with that spectrum.
    """
    from scipy import fft  # on first use (clip specs import this module for its version)

    length = int(fft.next_fast_len(max(n, NPERSEG), real=True))
    bins = np.fft.rfftfreq(length)  # cycles per sample, 0 .. 0.5
    shape = np.interp(bins, np.linspace(0.0, 0.5, len(spectrum)), spectrum)
    re_im = rng.standard_normal((2, len(bins)))
    x = fft.irfft(shape * (re_im[0] + 1j * re_im[1]), n=length)[:n]
    return x / max(float(np.sqrt(np.mean(x**2))), _FLOOR)


@dataclass(frozen=True)
class MixRecord:
    """What one clip's mix holds (levels measured on the mixed components)."""

    source: str
    snr_db: float  # asked
    speech_level_dbfs: float  # the speech's active level, measured after scaling
    noise_rms_dbfs: float  # the noise's RMS between its fades
    measured_snr_db: float
    peak_dbfs: float  # of the mix

    def to_json(self) -> dict:
        return {k: round(v, 4) if isinstance(v, float) else v for k, v in asdict(self).items()}


def mix_at_snr(
    speech: np.ndarray,
    noise: np.ndarray,
    *,
    sample_rate: int,
    snr_db: float,
    speech_level_dbfs: float,
    ramp_s: float,
    source: str,
) -> tuple[np.ndarray, MixRecord]:
    """``speech`` (the clip's whole sound, padding included) scaled to ``speech_level_dbfs``
    active level plus ``noise`` (RMS 1 or any, same length) scaled to ``snr_db`` below it over
    the clip, faded over ``ramp_s`` at both ends. Raises ValueError when the mix would clip."""
    speech = np.asarray(speech, dtype=np.float64)
    noise = np.asarray(noise, dtype=np.float64)[: len(speech)]
    if len(noise) < len(speech):
        raise ValueError("the noise is shorter than the clip")
    level = active_level_db(speech, sample_rate=sample_rate)
    s = speech * 10 ** ((speech_level_dbfs - level) / 20)
    ramp = min(round(ramp_s * sample_rate), len(noise) // 2)
    if ramp > 0:
        fade = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, ramp))
        noise = noise.copy()
        noise[:ramp] *= fade
        noise[-ramp:] *= fade[::-1]
    target = speech_level_dbfs - snr_db
    steady = noise[ramp : len(noise) - ramp] if len(noise) > 2 * ramp else noise
    n = noise * 10 ** ((target - rms_db(steady)) / 20)
    mix = s + n
    peak = float(np.max(np.abs(mix))) if len(mix) else 0.0
    if peak >= 1.0:
        raise ValueError(
            f"the mix at {snr_db:g} dB SNR would clip (peak {20 * np.log10(peak):+.1f} dBFS): "
            "lower noise.speech_level_dbfs"
        )
    record = MixRecord(
        source=source, snr_db=float(snr_db),
        speech_level_dbfs=active_level_db(s, sample_rate=sample_rate),
        noise_rms_dbfs=rms_db(n[ramp : len(n) - ramp] if len(n) > 2 * ramp else n),
        measured_snr_db=active_level_db(s, sample_rate=sample_rate)
        - rms_db(n[ramp : len(n) - ramp] if len(n) > 2 * ramp else n),
        peak_dbfs=float(20 * np.log10(max(peak, _FLOOR))),
    )  # fmt: skip
    return mix.astype(np.float32), record
