"""facelab.stimuli.speech: speech in, viseme tracks out.

* :mod:`.audio` - the :class:`Speech` and :class:`Phone` types, recorded audio files, resampling;
* :mod:`.tts` - Japanese text-to-speech with OpenJTalk (waveform and exact phoneme times);
* :mod:`.prosody` - words and accent phrases from OpenJTalk's front end;
* :mod:`.espeak` - eSpeak NG voices (a second synthesizer family for training and judging);
* :mod:`.track` - the :class:`VisemeTrack` type and the text-driven track;
* :mod:`.features` - the analyser's cepstral features;
* :mod:`.analyser` - the audio-only 15-viseme analyser (offline and streaming);
* :mod:`.align` - alignment of a recording to its known words (DTW, :mod:`.dtw`);
* :mod:`.vowels` - vowel segments, calibration on a speaker's vowels, vowel isolation;
* :mod:`.training` - the analyser's training corpus and fit.

The contract names of ``DESIGN.md`` (``visemes.analyze``, ``visemes.align``, ``VisemeTrack``)
stay importable from :mod:`facelab.stimuli.visemes`.
"""

from facelab.stimuli.speech.audio import (
    MIN_SAMPLE_RATE,
    Phone,
    Speech,
    SpeechError,
    check_audio,
    load_audio,
    resample,
    write_wav,
)
from facelab.stimuli.speech.tts import DICTIONARY_DIR, TTS_SAMPLE_RATE, synthesize, voice_file

__all__ = [
    "DICTIONARY_DIR",
    "MIN_SAMPLE_RATE",
    "TTS_SAMPLE_RATE",
    "Phone",
    "Speech",
    "SpeechError",
    "check_audio",
    "load_audio",
    "resample",
    "synthesize",
    "voice_file",
    "write_wav",
]
