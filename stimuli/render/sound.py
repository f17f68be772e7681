"""What a clip lets the participant hear: the stimulus' padded speech moved by the
condition's ``audio_offset_ms``, muted (``visual_only``), or mixed with its noise at the SNR
(:mod:`facelab.stimuli.speech.noise`). Shared by the render (which encodes it) and the
stimulus checks (which compare the decoded clip with it)."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from facelab.bounded_memo import BoundedMemo
from facelab.errors import StageError
from facelab.protocol import Protocol, Stimulus
from facelab.stimuli.render.clip import shifted_audio
from facelab.stimuli.render.clipspec import ClipJob
from facelab.stimuli.speech.audio import Speech, load_audio
from facelab.stimuli.speech.noise import (
    MixRecord,
    long_term_spectrum,
    mix_at_snr,
    noise_rng,
    shaped_noise,
)

__all__ = ["clip_sound"]

#: bytes of speech-shaped noise kept (:func:`_speech_shaped_noise`): the clips of one
#: stimulus at one SNR share their noise (one per modality or method), and the stimulus
#: checks make each clip's sound again after the render in the same process
NOISE_CACHE_BYTES = 256 * 2**20
_noises: BoundedMemo[np.ndarray] = BoundedMemo(max_bytes=NOISE_CACHE_BYTES,
                                               size_of=lambda x: x.nbytes)  # fmt: skip


def _speech_shaped_noise(spectrum: np.ndarray, *, n: int, parts: tuple[str, ...]) -> np.ndarray:
    """:func:`shaped_noise` of ``spectrum`` from the generator :func:`noise_rng` seeds with
    ``parts`` - the same numbers, computed once while they stay in a bounded cache (a long
    clip's token costs milliseconds, and the checks make each clip's sound again). Read-only."""
    key = (hashlib.sha1(spectrum.tobytes()).hexdigest(), n, parts)
    hit = _noises.get(key)
    if hit is not None:
        return hit
    made = shaped_noise(spectrum, n=n, rng=noise_rng(*parts))
    made.setflags(write=False)
    _noises.put(key, made)
    return made


def clip_sound(
    protocol: Protocol, job: ClipJob, audio: Speech, *, base_dir: Path,
    spectra: dict[str, np.ndarray], speech_of: Callable[[str, Stimulus], Speech],
) -> tuple[Speech, MixRecord | None]:  # fmt: skip
    """What a clip lets the participant hear: the padded speech moved by the condition's
    ``audio_offset_ms``, muted (visual_only), or mixed with its noise at the SNR."""
    cond = protocol.condition(job.condition)
    shown = shifted_audio(audio, offset_ms=cond.audio_offset_ms)
    if cond.modality == "visual_only":  # muted: the same length, silence
        return Speech(np.zeros_like(audio.samples), audio.sample_rate, source="muted"), None
    if cond.noise is None:
        return shown, None
    noise = cond.noise
    rate = audio.sample_rate
    parts = (protocol.study.id, job.stimulus_set, job.stimulus.id, f"{noise.snr_db:g}")
    n = len(shown.samples)
    if noise.source == "speech_shaped":
        if job.stimulus_set not in spectra:
            stimuli = protocol.stimulus_set(job.stimulus_set).stimuli
            spectra[job.stimulus_set] = long_term_spectrum(
                [speech_of(job.stimulus_set, st).samples for st in stimuli], sample_rate=rate)
        raw = _speech_shaped_noise(spectra[job.stimulus_set], n=n, parts=parts)
    else:
        loop = load_audio(base_dir / noise.source, sample_rate=rate).samples
        start = int(noise_rng(*parts).integers(len(loop)))
        raw = np.resize(np.roll(loop, -start), n)  # looped from a seeded point
    try:
        mixed, record = mix_at_snr(shown.samples, raw, sample_rate=rate, snr_db=noise.snr_db,
                                   speech_level_dbfs=noise.speech_level_dbfs,
                                   ramp_s=noise.ramp_s, source=noise.source)  # fmt: skip
    except ValueError as exc:
        raise StageError(f"{job.clip_id}: {exc}") from None
    return Speech(mixed, rate, shown.phones, f"{shown.source} in noise"), record
