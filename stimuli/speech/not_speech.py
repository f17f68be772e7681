"""Recordings that cannot be speech: a steady tone or noise given as a stimulus's ``audio``.
facelab would analyse either as speech and move the mouth to it; ``facelab validate`` and
``render`` refuse it at the stimulus's ``audio`` key instead. Pure numpy.

Speech spreads each short-time spectrum over harmonics and formants (voiced) or over a band
with a shape (fricatives, whispering). Over the sound's frames (32 ms, every 10 ms, within
:data:`ACTIVE_DB` dB of the loudest), a recording is refused as

* a **tone** when, in :data:`TONE_FRAMES` of its frames or more, :data:`TONE_SHARE` of the
  frame's energy above 50 Hz lies within :data:`TONE_HZ` of one frequency, the same
  throughout (a sine, beeps, a sine with vibrato or light noise);
* **noise** when, in :data:`NOISE_FRAMES` of its frames or more, the spectrum is as flat as
  white, pink or brown noise (spectral flatness :data:`NOISE_FLATNESS` or more over
  100 Hz - 8 kHz once a 0, -3 or -6 dB/octave tilt is taken off): speech 6 dB below white
  noise still shows in more frames than that allows; 12 dB below, it does not.

Measured (``tests/test_not_speech.py`` and the README): the most tone-like speech had 0.24
of its frames tone-like (a long synthetic うー), the flattest 0.17 flatness (whispered う);
tones and noises reach 0.9-1.0 and 0.5-0.6. Music is not judged.
"""

from __future__ import annotations

import numpy as np

__all__ = ["not_speech_reason"]

FRAME_S = 0.032
HOP_S = 0.010
ACTIVE_DB = 30.0  # frames within this of the loudest are the sound
TONE_HZ = 60.0
TONE_SHARE = 0.9
NOISE_FLATNESS = 0.35
TONE_FRAMES = 0.9  # the share of the sound's frames that must show the spectrum
NOISE_FRAMES = 0.97
LOW_HZ = 50.0  # below: the DC offset, rumble and brown noise's bulk, never a tone
MIN_SOUND_S = 0.2  # less sound than this is not judged


def not_speech_reason(samples: np.ndarray, *, sample_rate: int) -> str | None:
    """Why ``samples`` (mono, any level, ``sample_rate`` Hz) cannot be speech - a tone or
    noise, in words for an error message - or None (speech, music, or too little sound to
    tell)."""
    x = np.asarray(samples, dtype=np.float64)
    n = round(FRAME_S * sample_rate)
    hop = round(HOP_S * sample_rate)
    if len(x) < n + hop:
        return None
    starts = np.arange(0, len(x) - n + 1, hop)
    frames = x[starts[:, None] + np.arange(n)]
    frames = (frames - frames.mean(axis=1, keepdims=True)) * np.hanning(n)
    power = np.abs(np.fft.rfft(frames, axis=1)) ** 2  # (T, F)
    freqs = np.fft.rfftfreq(n, 1.0 / sample_rate)
    energy = power.sum(axis=1)
    top = float(energy.max())
    if top <= 0:
        return None
    p = power[energy >= top * 10 ** (-ACTIVE_DB / 10)]
    if len(p) * HOP_S < MIN_SOUND_S:
        return None
    above = p[:, freqs >= LOW_HZ]
    hz = freqs[freqs >= LOW_HZ]
    peak = np.argmax(above, axis=1)
    width = max(1, round(TONE_HZ / freqs[1]))
    near = np.abs(np.arange(above.shape[1])[None, :] - peak[:, None]) <= width
    share = (above * near).sum(axis=1) / np.maximum(above.sum(axis=1), top * 1e-16)
    centre = (above * near) @ hz / np.maximum((above * near).sum(axis=1), top * 1e-16)
    where = float(np.median(centre))  # each frame's peak, its energy centre (finer than bins)
    tonal = (share >= TONE_SHARE) & (np.abs(centre - where) <= TONE_HZ)
    if np.mean(tonal) >= TONE_FRAMES:
        return (f"a tone at {where:.0f} Hz ({100 * float(np.median(share)):.0f} % of its sound "
                f"within {TONE_HZ:g} Hz of it)")  # fmt: skip
    band = (freqs >= 100.0) & (freqs <= min(8000.0, sample_rate / 2 - 1))
    if band.sum() < 16:
        return None
    q = np.maximum(p[:, band], top * 1e-16)
    flatness = np.zeros(len(q))
    for tilt in (0.0, 1.0, 2.0):  # white, pink, brown made flat
        t = q * freqs[band] ** tilt
        flatness = np.maximum(flatness, np.exp(np.mean(np.log(t), axis=1)) / t.mean(axis=1))
    if np.mean(flatness >= NOISE_FLATNESS) >= NOISE_FRAMES:
        return ("noise (a spectrum as flat as white, pink or brown noise in "
                f"{100 * float(np.mean(flatness >= NOISE_FLATNESS)):.0f} % of its sound, "
                f"flatness {float(np.median(flatness)):.2f}; speech has harmonics and "
                "formants, and any speech in it lies far below the noise)")
    return None
