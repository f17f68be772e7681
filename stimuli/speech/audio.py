"""Speech audio: the :class:`Speech` and :class:`Phone` types, recorded audio files, resampling.

Recorded WAV/FLAC of any common rate and channel count is mixed to mono (mean of channels)
and resampled explicitly (polyphase, ``scipy.signal.resample_poly``) to the rate asked for.
Empty, silent, clipped or unreadable audio raises :class:`SpeechError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from itertools import pairwise
from pathlib import Path

import numpy as np

from facelab.errors import SpeechError
from facelab.stimuli.speech.prosody import (
    AccentPhrase,
    Word,
)

__all__ = [
    "MIN_SAMPLE_RATE",
    "Phone",
    "Speech",
    "SpeechError",
    "check_audio",
    "frame_chunks",
    "load_audio",
    "resample",
    "write_wav",
]

#: The lowest sample rate of a recording (and of the analyser's input): below it the second
#: formant of /i/ and /e/ (2-3 kHz) is lost, and resampling up cannot bring it back.
MIN_SAMPLE_RATE = 8_000
SILENT_RMS_DBFS = -60.0  # below this the whole file counts as silent
CLIPPED_FRACTION = 0.001  # more than 0.1 % of samples at full scale counts as clipped


def frame_chunks(count: int, *, at_most: int) -> list[tuple[int, int]]:
    """[start, stop) ranges covering ``count`` frames in nearly equal chunks of at most
    ``at_most`` (none of a single frame unless ``count`` is 1): long recordings are analysed
    chunk by chunk, so their windows and spectra never sit in memory at once."""
    bounds = np.linspace(0, count, -(-count // at_most) + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in pairwise(bounds)]


@dataclass(frozen=True)
class Phone:
    """One OpenJTalk phoneme: ``a i u e o`` (``A I U E O`` devoiced), consonants, ``N``,
    ``cl`` (geminate), ``pau`` and ``sil``. Times in seconds from the start of the audio."""

    phoneme: str
    start: float
    end: float


@dataclass(frozen=True)
class Speech:
    """A mono waveform and, for TTS, its phoneme timeline.

    samples : float32, shape (n,), in [-1, 1]; sample_rate in Hz.
    phones : tuple of :class:`Phone` (empty for recorded audio).
    words, accents : the front end's timed words and accent phrases
        (:mod:`facelab.stimuli.speech.prosody`; empty for recorded audio).
    """

    samples: np.ndarray
    sample_rate: int
    phones: tuple[Phone, ...] = ()
    source: str = ""
    words: tuple[Word, ...] = ()
    accents: tuple[AccentPhrase, ...] = ()

    @property
    def duration_s(self) -> float:
        return len(self.samples) / self.sample_rate


def _read_wav_pcm16(path: Path, *, data: bytes | None = None) -> tuple[np.ndarray, int]:
    """Mono samples and rate of a 16-bit PCM WAV: the file at ``path``, or its bytes ``data``
    (``path`` then only names it)."""
    import io
    import wave

    try:
        with wave.open(io.BytesIO(data) if data is not None else str(path), "rb") as fh:
            rate, width, channels, n = (
                fh.getframerate(),
                fh.getsampwidth(),
                fh.getnchannels(),
                fh.getnframes(),
            )
            raw = fh.readframes(n)
    except (wave.Error, EOFError) as exc:
        raise SpeechError(f"{path}: not a readable WAV ({exc})") from None
    if width != 2:
        raise SpeechError(f"{path}: expected 16-bit PCM from OpenJTalk, got {8 * width}-bit")
    if len(raw) != n * width * channels:
        raise SpeechError(f"{path}: cut short ({len(raw)} of {n * width * channels} bytes)")
    data = np.frombuffer(raw, dtype="<i2").astype(np.float32) / 32768.0
    return data.reshape(-1, channels).mean(axis=1), rate


def resample(samples: np.ndarray, *, rate_in: int, rate_out: int) -> np.ndarray:
    """Polyphase resampling with scipy's default Kaiser-windowed anti-alias filter."""
    if rate_in == rate_out:
        return samples.astype(np.float32, copy=False)
    from scipy import signal  # on first use: scipy.signal takes ~1.5 s to import

    ratio = Fraction(rate_out, rate_in)
    out = signal.resample_poly(samples.astype(np.float64), ratio.numerator, ratio.denominator)
    return out.astype(np.float32)


def check_audio(samples: np.ndarray, *, sample_rate: int, source: str) -> None:
    """Raise :class:`SpeechError` for empty, silent, clipped or non-finite audio."""
    if samples.size == 0:
        raise SpeechError(f"{source}: the audio is empty")
    if samples.size < sample_rate * 0.05:
        raise SpeechError(f"{source}: the audio is shorter than 50 ms")
    if not np.all(np.isfinite(samples)):
        raise SpeechError(f"{source}: the audio contains NaN or infinite samples")
    rms = float(np.sqrt(np.mean(np.square(samples, dtype=np.float64))))
    if rms == 0 or 20 * np.log10(rms) < SILENT_RMS_DBFS:
        level = "-inf" if rms == 0 else f"{20 * np.log10(rms):.1f}"
        raise SpeechError(f"{source}: the audio is silent (RMS {level} dBFS < {SILENT_RMS_DBFS:g})")
    clipped = float(np.mean(np.abs(samples) >= 0.999))
    if clipped > CLIPPED_FRACTION:
        raise SpeechError(
            f"{source}: the audio is clipped ({100 * clipped:.2f} % of samples at "
            "full scale); record again at a lower level"
        )


def _check_wav_length(path: Path) -> None:
    """A WAV whose data chunk is shorter than its header declares was cut off (a copy that
    did not finish): refused rather than read as a shorter recording."""
    with open(path, "rb") as fh:
        head = fh.read(12)
        if head[:4] != b"RIFF" or head[8:12] != b"WAVE":
            return  # not a WAV: the decoder says what it is
        size = path.stat().st_size
        offset = 12
        while offset + 8 <= size:
            fh.seek(offset)
            chunk, length = fh.read(4), int.from_bytes(fh.read(4), "little")
            if chunk == b"data":
                have = size - offset - 8
                if length > have and length != 0xFFFFFFFF:  # 0xFFFFFFFF: a stream
                    raise SpeechError(
                        f"{path}: truncated: its header declares {length} bytes of audio, the "
                        f"file holds {have} (a copy that did not finish?)"
                    )
                return
            offset += 8 + length + (length & 1)


def load_audio(path: Path | str, *, sample_rate: int) -> Speech:
    """A recorded WAV/FLAC file as mono float32 at ``sample_rate`` Hz, checked."""
    import soundfile as sf

    path = Path(path)
    if not path.is_file():
        raise SpeechError(f"{path}: audio file not found")
    size = path.stat().st_size
    if size == 0:
        raise SpeechError(f"{path}: the audio file is empty (0 bytes)")
    _check_wav_length(path)
    try:
        data, rate = sf.read(str(path), dtype="float32", always_2d=True)
    except (sf.LibsndfileError, RuntimeError, TypeError, ValueError):
        raise SpeechError(
            f"{path}: not a readable WAV/FLAC/OGG file ({size} bytes; the format is not "
            "recognised or the file is truncated or damaged)"
        ) from None
    if rate < MIN_SAMPLE_RATE:
        raise SpeechError(
            f"{path}: recorded at {rate} Hz; facelab needs at least {MIN_SAMPLE_RATE} Hz (the "
            "vowels' second formant lies at 2-3 kHz); record again at 16 kHz or more"
        )
    mono = data.mean(axis=1)
    if data.shape[1] > 1:  # channels that cancel: one of them recorded with its polarity flipped
        each = np.sqrt(np.mean(np.square(data, dtype=np.float64), axis=0))
        mixed = float(np.sqrt(np.mean(np.square(mono, dtype=np.float64))))
        if each.max() > 0 and mixed < 0.1 * float(each.max()):
            raise SpeechError(
                f"{path}: its {data.shape[1]} channels cancel when mixed to mono (the mix is "
                f"{min(100.0, -20 * np.log10(max(mixed, 1e-12) / float(each.max()))):.0f} dB "
                "or more below the loudest channel: one is recorded with its polarity "
                "inverted); give one "
                "channel (e.g. ffmpeg -i IN -af pan=mono|c0=c0 OUT.wav)"
            )
    check_audio(mono, sample_rate=rate, source=str(path))
    return Speech(
        samples=resample(mono, rate_in=rate, rate_out=sample_rate),
        sample_rate=sample_rate,
        source=str(path),
    )


def write_wav(path: Path, speech: Speech) -> None:
    """16-bit PCM WAV (used for clips and caches)."""
    import soundfile as sf

    sf.write(str(path), np.clip(speech.samples, -1, 1), speech.sample_rate, subtype="PCM_16")
