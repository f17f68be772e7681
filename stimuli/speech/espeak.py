"""A second Japanese synthesizer: eSpeak NG (formant synthesis) with its own phoneme timing.

OpenJTalk's ``mei`` is the only statistical Japanese voice that installs offline here; the
viseme analyser trained on it must still work on other voices. eSpeak NG (Debian
``espeak-ng``, GPL-3) synthesises Japanese kana with a formant synthesizer - a different
source, spectrum and timing model from mei - and its *voice variants* (``ja+f3``,
``ja+m2``, ``ja+klatt2``, …) change pitch and formant frequencies (a different vocal-tract
length) or the synthesis model (Klatt). With phoneme events switched on, the library reports
the sample at which each phoneme starts, so every utterance comes with exact labels, like
OpenJTalk's trace.

Text goes through OpenJTalk's front end first (kanji -> the words' katakana pronunciation,
punctuation kept as pauses), because eSpeak's Japanese voice reads only kana. The phonemes
eSpeak reports are mapped to OpenJTalk's names (:data:`PHONEME_MAP`) so the rest of facelab
(``frame_labels``, ``score_track``, ``from_phonemes``) reads them unchanged.

The library is driven through ``ctypes`` (``libespeak-ng.so.1``): one process-wide engine,
guarded by a lock; ``espeak_Synth`` in synchronous mode calls back with audio chunks and
events.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

import numpy as np

from facelab.errors import SpeechError
from facelab.stimuli.speech.audio import Phone, Speech, resample
from facelab.stimuli.speech.tts import synthesize

__all__ = ["ESPEAK_RATE", "PHONEME_MAP", "EspeakVoice", "espeak_synthesize", "kana_of"]

ESPEAK_RATE = 22_050  # the library's fixed output rate

#: eSpeak NG Japanese phoneme mnemonics -> OpenJTalk phoneme names. Long vowels (``a:``)
#: map to the vowel; ``_j`` (palatalisation after a consonant) to the glide ``y``; pauses
#: to ``pau``.
PHONEME_MAP = {
    **{v: v for v in "aiueo"},
    **{f"{v}:": v for v in "aiueo"},
    "N": "N",
    "N\\": "N",  # uvular, utterance-final
    "u~": "N",  # moraic nasal before a fricative, glide or vowel (a nasalised vowel)
    "k": "k",
    "g": "g",
    "s": "s",
    "z": "z",
    "dz": "z",
    "t": "t",
    "d": "d",
    "n": "n",
    "h": "h",
    "C": "h",
    "F": "f",
    "b": "b",
    "p": "p",
    "m": "m",
    "r": "r",
    "r`": "r",
    "j": "y",
    "_j": "y",  # palatalised consonant (kya, sho): the glide
    "w": "w",
    "S": "sh",
    "s\\": "sh",
    "tS": "ch",
    "t_s\\": "ch",
    "dZ": "j",
    "d_z\\": "j",
    "ts": "ts",
    "t_s": "ts",
    "p\\": "f",
    "_": "pau",
    "_:": "pau",
    "_!": "cl",
    "_^_": "pau",
}

# espeak_EVENT_TYPE values (speak_lib.h)
_EV_END_OF_LIST = 0
_EV_PHONEME = 7
_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),
        ("sample", ctypes.c_int),
        ("user_data", ctypes.c_void_p),
        ("id", _EventId),
    ]


_CALLBACK = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event)
)
_LOCK = threading.Lock()


@dataclass(frozen=True)
class EspeakVoice:
    """One eSpeak voice setting: ``variant`` ('' = the default male voice, else a name from
    eSpeak's ``voices/!v``, e.g. ``f3``, ``m2``, ``klatt2``), speaking ``rate`` in words per
    minute (80..450, eSpeak's default 175) and ``pitch`` 0..99 (default 50)."""

    variant: str = ""
    rate: int = 175
    pitch: int = 50

    def label(self) -> str:
        name = f"espeak_ja+{self.variant}" if self.variant else "espeak_ja"
        extra = "" if (self.rate, self.pitch) == (175, 50) else f"_r{self.rate}_p{self.pitch}"
        return name + extra


class _Engine:
    """The process-wide library handle (use under ``_LOCK``)."""

    def __init__(self) -> None:
        path = ctypes.util.find_library("espeak-ng") or "libespeak-ng.so.1"
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            raise SpeechError(
                "eSpeak NG is not installed (Debian: apt-get install espeak-ng; "
                "scripts/setup.sh installs it)"
            ) from None
        lib.espeak_Initialize.restype = ctypes.c_int
        lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
        lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
        lib.espeak_Synth.argtypes = [
            ctypes.c_char_p,
            ctypes.c_size_t,
            ctypes.c_uint,
            ctypes.c_int,
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.c_void_p,
            ctypes.c_void_p,
        ]
        rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, 0, None, _INITIALIZE_PHONEME_EVENTS)
        if rate != ESPEAK_RATE:
            raise SpeechError(f"eSpeak NG did not initialise (returned {rate})")
        self.lib = lib
        self.chunks: list[np.ndarray] = []
        self.events: list[tuple[int, str]] = []
        self._callback = _CALLBACK(self._on_audio)  # kept alive with the engine
        lib.espeak_SetSynthCallback(self._callback)

    def _on_audio(self, wav, n: int, events) -> int:
        if n > 0:
            self.chunks.append(np.ctypeslib.as_array(wav, shape=(n,)).astype(np.float32))
        i = 0
        while events[i].type != _EV_END_OF_LIST:
            ev = events[i]
            if ev.type == _EV_PHONEME:
                name = bytes(ev.id.string).split(b"\0")[0].decode("ascii", "replace")
                self.events.append((int(ev.sample), name))
            i += 1
        return 0

    @cached_property
    def variants(self) -> frozenset[str]:
        """Names of the voice variants installed (files of ``espeak-ng-data/voices/!v``),
        listed once per process."""
        path = ctypes.c_char_p()
        self.lib.espeak_Info.restype = ctypes.c_char_p
        self.lib.espeak_Info(ctypes.byref(path))
        folder = Path(path.value.decode()) / "voices" / "!v" if path.value else None
        if folder is None or not folder.is_dir():
            return frozenset()
        return frozenset(f.name for f in folder.iterdir() if f.is_file())

    def speak(self, kana: str, voice: EspeakVoice) -> tuple[np.ndarray, list[tuple[int, str]]]:
        name = f"ja+{voice.variant}" if voice.variant else "ja"
        if voice.variant and voice.variant not in self.variants:
            raise SpeechError(
                f"eSpeak NG has no voice {name!r} (variants are the files of "
                "espeak-ng-data/voices/!v, e.g. f3, m2, klatt2)"
            )
        if not (80 <= voice.rate <= 450 and 0 <= voice.pitch <= 99):
            raise SpeechError(
                f"eSpeak NG voice {voice.label()}: rate must be 80..450 wpm and pitch 0..99"
            )
        if self.lib.espeak_SetVoiceByName(name.encode()) != 0:
            raise SpeechError(f"eSpeak NG has no voice {name!r} (see espeak-ng --voices=ja)")
        self.lib.espeak_SetParameter(1, int(voice.rate), 0)  # espeakRATE
        self.lib.espeak_SetParameter(3, int(voice.pitch), 0)  # espeakPITCH
        self.chunks, self.events = [], []
        data = kana.encode("utf-8")
        # flags: espeakCHARS_UTF8 (1)
        if self.lib.espeak_Synth(data, len(data) + 1, 0, 0, 0, 1, None, None) != 0:
            raise SpeechError(f"eSpeak NG could not synthesise {kana[:30]!r}")
        self.lib.espeak_Synchronize()
        audio = np.concatenate(self.chunks) / 32768.0 if self.chunks else np.zeros(0)
        return audio.astype(np.float32), list(self.events)


@cache
def _engine() -> _Engine:
    return _Engine()


@cache
def kana_of(text: str) -> str:
    """The katakana pronunciation of Japanese ``text`` by OpenJTalk's front end (long vowels
    as ``ー``), punctuation kept (eSpeak pauses on it)."""
    words = synthesize(text).words
    return "".join(w.reading if w.morae else w.surface for w in words).replace("’", "")


def espeak_synthesize(
    text: str, *, voice: EspeakVoice = EspeakVoice(), sample_rate: int = 48_000
) -> Speech:
    """Japanese text -> :class:`Speech` spoken by eSpeak NG, with phones in OpenJTalk names.

    Each phone runs from its phoneme event's sample to the next one's (the last to the end
    of the audio); leading and trailing pauses are labelled ``sil``. Audio is resampled from
    eSpeak's 22.05 kHz to ``sample_rate``.
    """
    kana = kana_of(text)
    with _LOCK:
        audio, events = _engine().speak(kana, voice)
    if audio.size == 0 or not events:
        raise SpeechError(f"eSpeak NG produced no speech for {text[:30]!r}")
    end = len(audio) / ESPEAK_RATE
    phones: list[Phone] = []
    for k, (sample, name) in enumerate(events):
        stop = events[k + 1][0] / ESPEAK_RATE if k + 1 < len(events) else end
        start = sample / ESPEAK_RATE
        if stop <= start:
            continue
        if name not in PHONEME_MAP:
            raise SpeechError(f"eSpeak NG phoneme {name!r} has no OpenJTalk name (in {text!r})")
        phones.append(Phone(PHONEME_MAP[name], start, stop))
    if phones and phones[0].start > 0:
        phones.insert(0, Phone("sil", 0.0, phones[0].start))
    if phones and phones[-1].end < end:
        phones.append(Phone("sil", phones[-1].end, end))
    for i in (0, -1):
        if phones and phones[i].phoneme == "pau":
            phones[i] = Phone("sil", phones[i].start, phones[i].end)
    if sample_rate != ESPEAK_RATE:
        audio = resample(audio, rate_in=ESPEAK_RATE, rate_out=sample_rate)
    return Speech(
        samples=audio.astype(np.float32),
        sample_rate=sample_rate,
        phones=tuple(phones),
        source=f"espeak:{voice.label()}:{text}",
    )
