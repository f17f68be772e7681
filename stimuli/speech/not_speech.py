"""Recordings that cannot be speech: a steady tone given as a stimulus's ``audio``. facelab
would analyse it as speech and move the mouth to it; ``facelab validate`` and ``render``
refuse it at the stimulus's ``audio`` key instead. Pure numpy.

Speech spreads each short-time spectrum over harmonics and formants (voiced) or over a band
(fricatives, whispering). Over the loud frames (32 ms, every 10 ms, within
:data:`ACTIVE_DB` dB of the loudest), a recording is refused as a **tone** when, in
:data:`TONE_FRAMES` of its frames or more, :data:`TONE_SHARE` of the frame's energy above
50 Hz lies within :data:`TONE_HZ` of one frequency, the same throughout: a sine, beeps, a
sine with vibrato or light noise, a triangle wave.

Measured on material the rule was not set on (an independent run: Kokoro's five natural
Japanese voices, 20 utterances each from あ and ん to a passage, in 23 versions - resampled,
quieter, clipped, hummed, band-limited, mp3/opus/GSM, reverberant, in noise): none of 2,400
speech files was refused; the most tone-like had 63 % of its frames tone-like (a whispered
しーっ after an 8 kHz round trip), against 90 % for a refusal. Not refused: harmonic sounds
(buzzes, hums, square waves, sweeps, DTMF, melodies, chords, music) and noise. A noise rule
(a spectrum as flat as white or pink noise in nearly every frame) was tried and dropped: it
refused real speech in noise - short utterances even at +10 dB SNR, most at 0 dB.
"""

from __future__ import annotations

import numpy as np

from facelab.stimuli.speech.audio import frame_chunks

__all__ = ["not_speech_reason"]

FRAME_S = 0.032
HOP_S = 0.010
ACTIVE_DB = 15.0  # frames within this of the loudest are judged: a hum 20 dB under the
# voice, alone in long pauses, is not (a steady tone's frames are all near its loudest)
TONE_HZ = 60.0
TONE_SHARE = 0.9
TONE_FRAMES = 0.9  # the share of the sound's frames that must be tone-like
LOW_HZ = 50.0  # below: the DC offset, rumble and brown noise's bulk, never a tone
MIN_SOUND_S = 0.2  # less sound than this is not judged
CHUNK_FRAMES = 1000  # frames analysed at once (10 s: tens of MB at 48 kHz)


def not_speech_reason(samples: np.ndarray, *, sample_rate: int) -> str | None:
    """Why ``samples`` (mono, any level, ``sample_rate`` Hz) cannot be speech - a tone, in
    words for an error message - or None (speech, any other sound, or too little sound to
    tell)."""
    x = np.asarray(samples, dtype=np.float64)
    n = round(FRAME_S * sample_rate)
    hop = round(HOP_S * sample_rate)
    if len(x) < n + hop:
        return None
    starts = np.arange(0, len(x) - n + 1, hop)
    freqs = np.fft.rfftfreq(n, 1.0 / sample_rate)
    low = freqs >= LOW_HZ
    hz = freqs[low]
    width = max(1, round(TONE_HZ / freqs[1]))
    window = np.hanning(n)
    energy, share, centre = (np.empty(len(starts)) for _ in range(3))
    # per frame, in chunks (a 5-minute recording's whole spectrogram took about 1 GB)
    for a, b in frame_chunks(len(starts), at_most=CHUNK_FRAMES):
        frames = x[starts[a:b, None] + np.arange(n)]
        frames = (frames - frames.mean(axis=1, keepdims=True)) * window
        power = np.abs(np.fft.rfft(frames, axis=1)) ** 2  # (chunk, F)
        energy[a:b] = power.sum(axis=1)
        above = power[:, low]
        peak = np.argmax(above, axis=1)
        near = np.abs(np.arange(above.shape[1])[None, :] - peak[:, None]) <= width
        held = above * near
        tiny = np.finfo(float).tiny  # a silent frame is not active: any floor will do
        share[a:b] = held.sum(axis=1) / np.maximum(above.sum(axis=1), tiny)
        centre[a:b] = held @ hz / np.maximum(held.sum(axis=1), tiny)
    top = float(energy.max())
    if top <= 0:
        return None
    active = energy >= top * 10 ** (-ACTIVE_DB / 10)
    if active.sum() * HOP_S < MIN_SOUND_S:
        return None
    share, centre = share[active], centre[active]
    where = float(np.median(centre))  # each frame's peak, its energy centre (finer than bins)
    tonal = (share >= TONE_SHARE) & (np.abs(centre - where) <= TONE_HZ)
    if np.mean(tonal) >= TONE_FRAMES:
        return (f"a tone at {where:.0f} Hz ({100 * float(np.median(share)):.0f} % of its sound "
                f"within {TONE_HZ:g} Hz of it)")  # fmt: skip
    return None
