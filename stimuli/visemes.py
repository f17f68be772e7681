"""The viseme contract of ``DESIGN.md`` at its documented path: ``analyze``, ``align``,
``calibrate`` and the :class:`VisemeTrack` type. They live in :mod:`facelab.stimuli.speech`
(track, analyser, alignment, vowels); this module re-exports them.
"""

from facelab.stimuli.speech.align import Alignment, align, align_phones
from facelab.stimuli.speech.analyser import (
    StreamingAnalyzer,
    VisemeModel,
    analyze,
    choose_warp,
    default_model,
)
from facelab.stimuli.speech.track import (
    VISEMES,
    VOWEL_VISEMES,
    VOWELS,
    VisemeTrack,
    from_phonemes,
    phoneme_viseme,
)
from facelab.stimuli.speech.vowels import calibrate, isolate_vowels, vowel_segments

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
