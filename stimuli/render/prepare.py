"""From a protocol stimulus to speech and viseme tracks: the shared first steps of rendering,
inspection (``facelab track``) and the demo."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facelab.errors import VisemeError
from facelab.protocol import Protocol, Stimulus
from facelab.stimuli.speech.align import align_phones
from facelab.stimuli.speech.analyser import analyze
from facelab.stimuli.speech.audio import Speech, load_audio
from facelab.stimuli.speech.track import VisemeTrack, from_phonemes
from facelab.stimuli.speech.tts import synthesize
from facelab.stimuli.speech.vowels import isolate_vowels, vowel_stretches

__all__ = [
    "find_stimulus",
    "speech_for",
    "track_source_text",
    "tracks_for",
]


def find_stimulus(protocol: Protocol, ref: str) -> tuple[str, Stimulus]:
    """``SET/ID`` (or a unique ``ID``) -> (set id, stimulus)."""
    from facelab.errors import StageError

    set_id, _, stim_id = ref.rpartition("/")
    hits = [
        (s.id, st)
        for s in protocol.stimulus_sets
        for st in s.stimuli
        if st.id == stim_id and set_id in ("", s.id)
    ]
    if len(hits) != 1:
        known = ", ".join(f"{s.id}/{st.id}" for s in protocol.stimulus_sets for st in s.stimuli)
        raise StageError(
            f"stimulus {ref!r} {'is ambiguous' if hits else 'not found'}; stimuli: {known}"
        )
    return hits[0]


def speech_for(stimulus: Stimulus, *, base_dir: Path, sample_rate: int) -> Speech:
    """TTS for a text stimulus (with its phoneme timeline), or the recording, at ``sample_rate``."""
    if stimulus.silence_s is not None:
        n = round(stimulus.silence_s * sample_rate)
        return Speech(np.zeros(n, np.float32), sample_rate, source="silence")
    if stimulus.text is not None:
        return synthesize(
            stimulus.text,
            speed=stimulus.tts.speed,
            pitch_halftones=stimulus.tts.pitch_halftones,
            alpha=stimulus.tts.alpha,
            sample_rate=sample_rate,
        )
    speech = load_audio(base_dir / str(stimulus.audio), sample_rate=sample_rate)
    if stimulus.transcript is None:
        return speech
    try:
        aligned = align_phones(speech.samples, sample_rate=sample_rate, text=stimulus.transcript)
    except VisemeError as exc:
        raise VisemeError(f"stimulus {stimulus.id!r} ({stimulus.audio}): {exc}") from None
    return Speech(
        speech.samples,
        speech.sample_rate,
        phones=aligned.phones,
        source=speech.source,
        words=aligned.words,
        accents=aligned.accents,
    )


def track_source_text(stimulus: Stimulus) -> str:
    """What made a stimulus' track, in words (each clip's JSON ``track_source``)."""
    source = stimulus.track_source
    if source == "words":
        return (
            "words: the synthesiser's phoneme timing of the text"
            if stimulus.text is not None
            else "words: phonemes of the transcript aligned to the recording"
        )
    if source == "audio":
        return "audio analysis" + (" (track_from: audio)" if stimulus.track_from else "")
    return "silence"


def tracks_for(stimulus: Stimulus, speech: Speech) -> tuple[VisemeTrack, VisemeTrack | None]:
    """(the stimulus' viseme track, vowel-isolated track or None). With the words
    (``Stimulus.track_source``), the track follows the phonemes - the synthesiser's timing
    for TTS, the transcript aligned to a recording - with no latency; else it is the
    audio-only analysis with its latency removed."""
    if stimulus.track_source == "words" and speech.phones:
        track = from_phonemes(speech.phones, duration_s=speech.duration_s)
    else:
        track = analyze(speech.samples, sample_rate=speech.sample_rate).compensated()
    isolated = None
    if stimulus.vowel_isolation and stimulus.expected_vowels:
        try:
            stretches = vowel_stretches(track, vowels=stimulus.expected_vowels,
                                        phones=speech.phones)  # fmt: skip
        except VisemeError as exc:
            raise VisemeError(f"stimulus {stimulus.id!r}: {exc}") from None
        isolated = isolate_vowels(track, vowels=stimulus.expected_vowels, segments=stretches)
    return track, isolated
