"""The protocol model: typed, frozen pydantic models of a study file, and its JSON Schema.

A protocol is one YAML file describing a whole study: metadata, conditions (an animation
method from :data:`facelab.methods.METHODS` plus its parameters), stimulus sets, blocks,
VAS items, presentation and rendering settings, and the seed. Unknown keys are errors
everywhere (``extra="forbid"``); values are checked strictly (no silent coercion).

This module only declares the shape. Reading YAML with line numbers is
:mod:`facelab.protocol_yaml`, checks that span sections are :mod:`facelab.protocol_checks`,
and :func:`facelab.protocol.load_protocol` puts them together. The JSON Schema of the format
is :func:`json_schema`; ``protocols/schema/protocol.schema.json`` is generated from it
(``facelab schema``) and a test keeps the two identical.
"""

from __future__ import annotations

import json
import unicodedata
from functools import cached_property
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)
from pydantic.json_schema import SkipJsonSchema

from facelab.emotions import BEHAVIOUR_MODES, EMOTIONS, emotion_of
from facelab.methods import BUILTIN_METHODS, method_spec

__all__ = [
    "AUDIO_SUFFIXES",
    "AVATAR_SUFFIXES",
    "ID_PATTERN",
    "SCHEMA_VERSION",
    "AnyTask",
    "Block",
    "ChoiceTask",
    "Condition",
    "IdentifyTask",
    "Label",
    "MatrixTask",
    "Noise",
    "Protocol",
    "Rendering",
    "SrtListener",
    "StaircaseRule",
    "Stimulus",
    "StimulusSet",
    "TimingJudgment",
    "TimingObserver",
    "TypedTask",
    "VasItem",
    "json_schema",
    "schema_json_text",
]

SCHEMA_VERSION = 1

#: Ids: a letter, then letters, digits, ``-`` or single ``_`` - never ``__``, which separates
#: the parts of clip file names (``<set>__<stimulus>__<condition>.mp4``), so two different
#: clips can never share a file name.
ID_PATTERN = r"^[A-Za-z](?:_?[A-Za-z0-9-])*_?$"
Id = Annotated[
    str,
    StringConstraints(pattern=ID_PATTERN, max_length=64),
    Field(
        description="An identifier: a letter, then letters, digits, - or single _ (no __), "
        "at most 64 characters."
    ),
]
LANG_PATTERN = r"^[a-z]{2,3}(-[A-Za-z0-9]+)?$"
LangCode = Annotated[str, StringConstraints(pattern=LANG_PATTERN)]
VOWELS_PATTERN = r"^[aiueo]+$"
Text = Annotated[str, StringConstraints(min_length=1)]
Localized = Annotated[
    dict[LangCode, Text],
    Field(
        min_length=1,
        description="Text by language code, e.g. {ja: 自然な表情, en: natural expression}.",
    ),
]
AUDIO_SUFFIXES = (".wav", ".flac")
AVATAR_SUFFIXES = (".gltf", ".glb", ".vrm")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


# --------------------------------------------------------------------------- study & conditions


class Study(_Model):
    """Who and what: identifies the study in every log row and report."""

    id: Id = Field(description="Short study id; results go to results/<id>/.")
    title: Text
    description: str = ""
    reference: str = Field("", description="The publication this protocol reproduces, if any.")
    participants_planned: int = Field(ge=1, le=10_000)
    notes: str = ""


class Noise(_Model):
    """Noise mixed with a condition's voice (speech-in-noise tasks). The speech is set to
    ``speech_level_dbfs`` (its active level: the RMS of its 20 ms frames within 40 dB of the
    loudest) in every clip, so loudness does not cue the SNR; the noise's RMS (over the clip,
    its fades left out) is ``snr_db`` below it. Each stimulus gets its own noise token, the
    same for every method at one SNR (the methods differ only in the face)."""

    snr_db: float = Field(ge=-40, le=40, description="Speech level minus noise level, dB.")
    source: str = Field(
        "speech_shaped",
        description="speech_shaped: Gaussian noise with the long-term average spectrum of the "
        "stimulus set's speech; or a noise file (WAV/FLAC, relative to the protocol; looped, "
        "a seeded stretch per clip).",
    )
    speech_level_dbfs: float = Field(
        -35.0,
        ge=-60,
        le=-6,
        description="The speech's active level in every clip, dBFS: low enough that the noise "
        "of the lowest SNR does not clip (Gaussian noise peaks about 13 dB above its RMS).",
    )
    ramp_s: float = Field(
        0.05, ge=0, le=1, description="Raised-cosine fade of the noise at the clip's ends."
    )


class Condition(_Model):
    """One animation condition: a registered method and its parameters."""

    id: Id
    label: Localized
    method: str = Field(description=f"One of: {', '.join(BUILTIN_METHODS)}, or an installed "
                        "plugin's method (facelab plugins lists them).")  # fmt: skip
    params: dict[str, Any] = Field(
        default_factory=dict,
        description="Parameters of the method; see facelab.methods.",
    )
    level: float | None = Field(
        None,
        description="The condition's position on a graded stimulus dimension (e.g. the "
        "impression level q); needed by constant_stimuli and staircase blocks, and used as x "
        "by the psychometric and trend analyses.",
    )
    behaviour: str = Field(
        "none",
        description="The non-verbal behaviour layer (seed 003) added to the speech animation: "
        f"{', '.join(BEHAVIOUR_MODES)}, or a behaviour library file (JSON/YAML, relative to "
        "the protocol) planned as composite.",
    )
    modality: Literal["audiovisual", "visual_only", "audio_only"] = Field(
        "audiovisual",
        description="What the clips of this condition give: audiovisual (face and voice), "
        "visual_only (the face, muted: lip-reading) or audio_only (the voice with a still "
        "face: the method's animation is not shown; or no face with rendering."
        "audio_only_face: none).",
    )
    audio_offset_ms: float = Field(
        0.0,
        ge=-2000,
        le=2000,
        description="The voice's offset against the face, ms: negative = the voice comes "
        "first, positive = it follows the mouth (audio-visual synchrony tasks). Conditions "
        "alike but for this offset share one rendered video, the sound shifted and re-muxed; "
        "at most rendering.pad_s, so no speech is cut.",
    )
    noise: Noise | None = Field(
        None,
        description="Noise mixed with the voice at an SNR (speech in noise); its snr_db is the "
        "condition's level unless 'level' is given. Conditions alike but for their noise share "
        "one rendered picture.",
    )
    series: Id | None = Field(
        None,
        description="The conditions analysed together as one function of audio_offset_ms - "
        "e.g. one animation method at every offset of a synchrony task: the timing analysis "
        "fits one window per participant and series (sync_window.csv's 'condition'). "
        "Default: the condition's own id.",
    )
    emotion: dict[str, float] | list[dict[str, float]] | None = Field(
        None,
        description=f"The character's emotion for this condition ({', '.join(EMOTIONS)}: 0..1; "
        "neutral follows eq. 4), or a timeline of keys [{time_s: s, joy: 0.8}, …] (seconds in "
        "the clip, linearly interpolated, held before the first and after the last key); "
        "omitted: the stimulus's emotion, else neutral.",
    )

    @model_validator(mode="before")
    @classmethod
    def _level_from_snr(cls, data: Any) -> Any:
        """A noise condition's level is its SNR unless the protocol gives one."""
        if isinstance(data, dict) and data.get("level") is None:
            noise = data.get("noise")
            snr = noise.get("snr_db") if isinstance(noise, dict) else None
            if isinstance(snr, int | float) and not isinstance(snr, bool):
                data = {**data, "level": float(snr)}
        return data

    @property
    def series_id(self) -> str:
        """The series this condition belongs to (its own id unless ``series`` names one)."""
        return self.series or self.id

    @cached_property
    def settings(self) -> Any:
        """The method's typed parameters (its registered parameter model), validated once.

        Raises ``pydantic.ValidationError`` for parameters the method does not accept and
        ``KeyError`` for an unregistered method; a loaded protocol has neither (its checks
        report both with the file's line)."""
        spec = method_spec(self.method)
        if spec is None:
            raise KeyError(self.method)
        return spec.parse(self.params)

    @model_validator(mode="after")
    def _behaviour(self) -> Condition:
        if self.behaviour not in BEHAVIOUR_MODES and not self.behaviour.lower().endswith(
            (".json", ".yaml", ".yml")
        ):
            raise ValueError(
                f"behaviour {self.behaviour!r}: use {', '.join(BEHAVIOUR_MODES)} or a library "
                "file ending in .json/.yaml"
            )
        if self.emotion is not None:
            emotion_of(self.emotion)
        return self


# --------------------------------------------------------------------------- stimuli


class TtsOptions(_Model):
    """OpenJTalk synthesis options for a text stimulus."""

    voice: Literal["mei_normal"] = "mei_normal"
    speed: float = Field(1.0, ge=0.5, le=2.0, description="Speaking rate factor (open_jtalk -r).")
    pitch_halftones: float = Field(0.0, ge=-12, le=12, description="Pitch shift (open_jtalk -fm).")
    alpha: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        description="All-pass constant, a voice-quality change (open_jtalk -a).",
    )


class Stimulus(_Model):
    """One stimulus: a text for TTS, a recorded audio file, or silence of a given length
    (expression clips without speech, e.g. impression levels)."""

    id: Id
    text: Text | None = Field(None, description="Japanese text to synthesise.")
    audio: Text | None = Field(None, description="WAV or FLAC file, relative to the protocol.")
    transcript: Text | None = Field(
        None,
        description="The words spoken in 'audio' (Japanese): its viseme track then comes from "
        "aligning the text's phonemes to the recording instead of audio-only analysis.",
    )
    silence_s: float | None = Field(
        None, gt=0, le=60, description="A silent stimulus of this many seconds (no speech)."
    )
    track_from: Literal["words", "audio"] | None = Field(
        None,
        description="Where the viseme track comes from: 'words' (the phoneme timing of "
        "'text', or of 'transcript' aligned to 'audio') or 'audio' (audio-only analysis, as a "
        "live lip-sync plug-in hears it). Default: the words whenever they are known.",
    )
    tts: TtsOptions = Field(default_factory=TtsOptions)
    expected_vowels: Annotated[str, StringConstraints(pattern=VOWELS_PATTERN)] | None = Field(
        None,
        description="The vowels spoken, in order (e.g. aiueo; はい is ai, です eu): validate "
        "checks them against OpenJTalk's reading of 'text' or 'transcript'. Needed for vowel "
        "isolation; the articulation checks look at each vowel's peak.",
    )
    vowel_isolation: list[Id] = Field(
        default_factory=list,
        description="Condition ids for which only the intended vowel's intensity is kept in "
        "each vowel segment (the rest set to 0).",
    )
    emotion: dict[str, float] | list[dict[str, float]] | None = Field(
        None,
        description=f"The emotion the stimulus is spoken with ({', '.join(EMOTIONS)}: 0..1), "
        "or a timeline of keys [{time_s: s, joy: 0.8}, …] (seconds in the clip), for "
        "conditions with a behaviour layer.",
    )
    note: str = ""

    @model_validator(mode="after")
    def _one_source(self) -> Stimulus:
        if sum(v is not None for v in (self.text, self.audio, self.silence_s)) != 1:
            raise ValueError(
                "give exactly one of 'text' (for TTS), 'audio' (a recording) or 'silence_s'"
            )
        if self.transcript is not None and self.audio is None:
            raise ValueError("'transcript' belongs to a recording: give it with 'audio'")
        if self.track_from == "words" and self.text is None and self.transcript is None:
            raise ValueError(
                "track_from: words needs the words: give the recording its 'transcript'"
            )
        if self.track_from is not None and self.silence_s is not None:
            raise ValueError("'track_from' is for speech; a 'silence_s' stimulus has no track")
        if self.vowel_isolation and self.expected_vowels is None:
            raise ValueError("'vowel_isolation' needs 'expected_vowels' (e.g. aiueo)")
        if self.emotion is not None:
            emotion_of(self.emotion)
        return self

    @property
    def track_source(self) -> Literal["words", "audio", "silence"]:
        """Where this stimulus' viseme track comes from (``track_from``, else the words when
        known): every method is driven from it, and each clip's JSON records it."""
        if self.silence_s is not None:
            return "silence"
        if self.track_from is not None:
            return self.track_from
        return "words" if (self.text is not None or self.transcript is not None) else "audio"


class StimulusSet(_Model):
    id: Id
    description: str = ""
    stimuli: list[Stimulus] = Field(min_length=1)


# --------------------------------------------------------------------------- blocks & items

Order = Literal["random_within_set", "fixed", "latin_square"]


class Label(_Model):
    """One answer of an identification task."""

    id: Id
    text: Localized


class ChoiceTask(_Model):
    """Two clips of the same stimulus, the block's standard and a comparison, one after the
    other or side by side; the participant picks one (key 1/2 or a click). Which one comes
    first (or left) is counterbalanced in the design and logged (``position``)."""

    id: Id
    type: Literal["choice_2afc"]
    question: Localized = Field(description="e.g. {en: Which face looked more natural?}.")
    standard: Id = Field(description="The condition every comparison is paired with.")
    correct: Literal["comparison", "none"] = Field(
        "comparison",
        description="comparison: choosing the comparison is the correct answer (detection or "
        "discrimination; guess rate 1/2); none: a preference, no answer is correct (guess "
        "rate 0).",
    )
    layout: Literal["sequential", "side_by_side"] = Field(
        "sequential",
        description="sequential: the two clips one after the other; side_by_side: both at "
        "once, left and right (position 1 = left), with the standard's sound (the clips of "
        "one stimulus share its speech; silent clips suit this layout best).",
    )
    gap_s: float = Field(
        0.5, ge=0.0, le=10.0, description="sequential: blank between the two clips."
    )


class TimingJudgment(_Model):
    """What an identify task's answers say about audio-visual timing, for the timing analysis
    over the conditions' ``audio_offset_ms``."""

    judgment: Literal["simultaneity", "temporal_order"] = Field(
        description="simultaneity: 'were voice and mouth in sync?' (the window of "
        "simultaneity: a Gaussian over the offset, its centre the point of subjective "
        "simultaneity, its full width at half its peak the window); temporal_order: 'which "
        "came first?' (a cumulative Gaussian: its 50 % point the PSS, the distance between "
        "its 25 % and 75 % points the width)."
    )
    label: Id = Field(
        description="simultaneity: the label meaning 'in sync'; temporal_order: the label "
        "meaning 'the voice came first'."
    )
    floor: Literal["fit", "none"] = Field(
        "fit",
        description="simultaneity: fit a floor - 'in sync' answers far outside the window "
        "(guesses, a bias to say yes) - below the window (fit), or assume none (none: such "
        "answers then widen the window).",
    )


class IdentifyTask(_Model):
    """One clip, then a choice among labels (e.g. the seven emotions)."""

    id: Id
    type: Literal["identify"]
    question: Localized = Field(description="e.g. {en: Which emotion did the face show?}.")
    labels: list[Label] = Field(min_length=2, max_length=9, description="Keys 1..9 choose.")
    answers: dict[Id, Id] = Field(
        default_factory=dict,
        description="Condition id or stimulus id -> the label it portrays (a condition's "
        "entry wins); scores answers as correct.",
    )

    timing: TimingJudgment | None = Field(
        None,
        description="The answers judge audio-visual timing (a synchrony task): the analysis "
        "fits each participant's window per condition series over audio_offset_ms "
        "(sync_window.csv).",
    )

    def target(self, *, condition: str, stimulus: str | None = None) -> str | None:
        """The label a trial portrays: by its condition, else by its stimulus."""
        if condition in self.answers:
            return self.answers[condition]
        return self.answers.get(stimulus) if stimulus is not None else None


class TypedTask(_Model):
    """One clip, then the participant types what was said (open-set speech recognition, e.g.
    words or sentences in noise). The answer is stored as typed (``response``) and scored as
    pronounced (:mod:`facelab.analysis.typed_scoring`): ``score`` is the share of the scoring
    units reproduced, ``correct`` 1 when all were. Needs a keyboard: not in VR."""

    id: Id
    type: Literal["typed"]
    question: Localized = Field(description="e.g. {ja: 聞こえた言葉を入力してください}.")
    scoring: Literal["keywords", "morae"] = Field(
        "keywords",
        description="keywords: the share of the stimulus' keywords found in the answer (as "
        "pronounced; with tolerant, one wrong mora in a keyword of three or more morae); "
        "morae: the share of the said morae the answer reproduces in order.",
    )
    answers: dict[Id, Text] = Field(
        default_factory=dict,
        description="Stimulus id -> what was said, when not the stimulus' text or transcript.",
    )
    keywords: dict[Id, list[Text]] = Field(
        default_factory=dict,
        description="Stimulus id -> its keywords (scoring: keywords); default the words of "
        "what was said, split at spaces (a text without spaces is one keyword).",
    )
    tolerant: bool = Field(
        False,
        description="A keyword of three or more morae also counts with one mora wrong (a "
        "typo) - but one wrong mora is also what mishearing makes (白い シロイ / 黒い "
        "クロイ), so off by default in a listening task.",
    )
    max_length: int = Field(
        80, ge=1, le=200, description="Characters the answer field takes."
    )

    def said(self, stimulus: Stimulus) -> str | None:
        """What the participant heard in ``stimulus``: the task's answer, else the text."""
        return self.answers.get(stimulus.id) or stimulus.text or stimulus.transcript

    def keywords_of(self, stimulus: Stimulus) -> list[str] | None:
        """The keywords an answer to ``stimulus`` is scored on (None: the words said)."""
        words = self.keywords.get(stimulus.id)
        return list(words) if words else None


#: What a matrix answer's words are cut from when taken from a stimulus' text: punctuation
#: at a word's ends (the text is read by the TTS with it).
_WORD_PUNCTUATION = "、。，．！？「」『』・,.!?\"'"


class MatrixTask(TypedTask):
    """A closed-set sentence test (a matrix test: Hagerman 1982; Wagener, Brand & Kollmeier
    1999): every sentence takes one word from each column of a word matrix, the participant
    sees the matrix after the clip and picks one word in each column (a guess where unsure).
    The picks are stored as the answer, words joined by spaces (``response``), and scored
    word by word against what was said: ``score`` is the share of the columns picked right,
    ``correct`` 1 when all were; a word is right by chance once in each column's length.
    Shown in the lab window and the browser, not in VR."""

    type: Literal["matrix"]  # type: ignore[assignment]
    # a typed task's keys, refused on a matrix (see the validator) and left out of its schema
    scoring: SkipJsonSchema[Literal["keywords", "morae"]] = "keywords"
    keywords: SkipJsonSchema[dict[Id, list[Text]]] = Field(default_factory=dict)
    tolerant: SkipJsonSchema[bool] = False
    max_length: SkipJsonSchema[int] = 80
    question: Localized = Field(description="e.g. {ja: 聞こえた文の言葉を選んでください}.")
    columns: list[Annotated[list[Text], Field(min_length=3, max_length=12)]] = Field(
        min_length=2,
        max_length=8,
        description="The word matrix: columns of 3-12 alternatives (e.g. 5 columns of 10 "
        "words: name, number, adjective, object, verb), in the order they are said; a word "
        "at most 64 characters, without spaces or punctuation at its ends.",
    )
    answers: dict[Id, Text] = Field(
        default_factory=dict,
        description="Stimulus id -> the words said, one per column, separated by spaces, "
        "when not the stimulus' text (written with spaces between the words; punctuation "
        "at the words' ends is dropped).",
    )

    @model_validator(mode="after")
    def _distinct_words(self) -> MatrixTask:
        typed_only = sorted(self.model_fields_set & {"scoring", "keywords", "tolerant",
                                                      "max_length"})  # fmt: skip
        if typed_only:
            raise ValueError(f"{', '.join(typed_only)}: for a typed task; a matrix answer is "
                             "scored word by word against the columns")  # fmt: skip
        for i, column in enumerate(self.columns):
            seen = {w for w in column if column.count(w) > 1}
            if seen:
                raise ValueError(f"column {i + 1} lists {', '.join(sorted(seen))} twice")
            for w in column:
                if (any(ch.isspace() or unicodedata.category(ch) in ("Cc", "Cf") for ch in w)
                        or len(w) > 64 or w.strip(_WORD_PUNCTUATION) != w):  # fmt: skip
                    raise ValueError(
                        f"column {i + 1}: {w!r}: a word is at most 64 characters, without "
                        "spaces, control characters or punctuation at its ends (a "
                        "participant could never pick it right)"
                    )
        return self

    def words_said(self, stimulus: Stimulus) -> list[str] | None:
        """The words said in ``stimulus``, one per column (None: nothing known)."""
        said = self.said(stimulus)
        if said is None:
            return None
        words = [w.strip(_WORD_PUNCTUATION) for w in said.split()]
        return [w for w in words if w]

    def guess_rate(self) -> float:
        """P(a word right by guessing), over the columns: the mean of 1 / column length."""
        return sum(1.0 / len(c) for c in self.columns) / len(self.columns)


Task = Annotated[
    ChoiceTask | IdentifyTask | TypedTask | MatrixTask, Field(discriminator="type")
]
AnyTask = ChoiceTask | IdentifyTask | TypedTask | MatrixTask


class StaircaseRule(_Model):
    """An adaptive rule over the block's conditions ordered by level: a transformed up-down
    staircase, or QUEST+ (Watson, 2017) over a grid of psychometric functions."""

    rule: Literal["up_down", "quest_plus", "brand_kollmeier"] = Field(
        "up_down",
        description="up_down: after 'down' correct answers in a row one step harder, after "
        "'up' wrong answers one step easier; quest_plus: each trial at the level that "
        "minimises the expected entropy of the posterior over (threshold, slope, lapse); "
        "brand_kollmeier: the level moves by -f(i) (score - target_score) / assumed_slope "
        "after each sentence, score the share of its words understood, f(i) = step_start "
        "step_decay^-i after i reversals (Brand & Kollmeier 2002), shown at the nearest "
        "grid level.",
    )
    start: Id | None = Field(
        None,
        description="The condition of the first trial (an easy one). Needed by up_down; "
        "quest_plus chooses its first level itself unless a start is given.",
    )
    up: int = Field(
        1, ge=1, le=5, description="up_down: wrong answers in a row before it gets easier."
    )
    down: int = Field(
        2, ge=1, le=5, description="up_down: correct answers in a row before it gets harder."
    )
    step: int = Field(1, ge=1, le=10, description="up_down: grid steps per move.")
    trials: int = Field(ge=2, le=1000, description="Trials of the staircase.")
    easier: Literal["higher", "lower"] = Field(
        "higher", description="Which end of the level scale is easier to answer correctly."
    )
    sigmoid: Literal["logistic", "weibull"] = Field(
        "logistic",
        description="quest_plus: the psychometric function F (weibull needs levels > 0 and "
        "easier: higher).",
    )
    threshold_points: int = Field(
        41,
        ge=5,
        le=201,
        description="quest_plus: threshold (alpha) values, evenly spaced from the lowest to "
        "the highest level of the block.",
    )
    slopes: list[Annotated[float, Field(gt=0)]] | None = Field(
        None,
        min_length=1,
        max_length=50,
        description="quest_plus: slope (beta) values; default 9 values, logistic: "
        "geometrically from 2 to 50 per level range, weibull: from 1 to 10.",
    )
    lapse_rates: list[Annotated[float, Field(ge=0, le=0.2)]] = Field(
        [0.0, 0.01, 0.02, 0.04],
        min_length=1,
        max_length=20,
        description="quest_plus: lapse-rate (lambda) values.",
    )
    target_score: float = Field(
        0.5, gt=0, lt=1, description="brand_kollmeier: the share of words right it tracks."
    )
    assumed_slope: float = Field(
        0.15,
        gt=0,
        le=1,
        description="brand_kollmeier: the intelligibility function's slope at the target "
        "(proportion per level unit, e.g. per dB), which turns a score's distance from the "
        "target into a level change.",
    )
    step_start: float = Field(1.5, gt=0, le=10, description="brand_kollmeier: f before the "
                              "first reversal.")  # fmt: skip
    step_decay: float = Field(1.41, ge=1, le=4, description="brand_kollmeier: f is divided by "
                              "this at each reversal.")  # fmt: skip
    step_min: float = Field(0.1, ge=0, le=10, description="brand_kollmeier: the smallest f "
                            "(0: none).")  # fmt: skip


class Block(_Model):
    """A run of sets; each set shows every (stimulus, condition) pair a fixed number of times."""

    id: Id
    stimulus_set: Id
    sets: int = Field(ge=1, le=100, description="How many sets the block has.")
    presentations_per_condition: int = Field(
        ge=1, le=100, description="How often each condition is shown per stimulus in one set."
    )
    order: Order = Field(
        "random_within_set",
        description="random_within_set: shuffled anew in every set; fixed: protocol order; "
        "latin_square: condition order from a balanced Latin square row chosen by the "
        "participant number (needs ids ending in a number).",
    )
    conditions: list[Id] | None = Field(
        None,
        description="Subset of conditions; default all (for a choice_2afc task all but its "
        "standard).",
    )
    break_after: bool = Field(True, description="Offer a break screen after this block.")
    task: Id | None = Field(
        None, description="A task id from 'tasks'; default: the VAS items after each clip."
    )
    design: Literal["factorial", "constant_stimuli", "staircase"] = Field(
        "factorial",
        description="factorial: every stimulus x condition per set; constant_stimuli: the "
        "same over conditions that are levels of one dimension (each needs a level), in "
        "random order; staircase: an adaptive rule picks each trial's level.",
    )
    staircase: StaircaseRule | None = Field(None, description="The rule of a staircase block.")


class VasItem(_Model):
    """One visual analogue scale item shown after each clip."""

    id: Id
    question: Localized
    left_anchor: Localized
    right_anchor: Localized
    range: list[float] = Field(
        default_factory=lambda: [0.0, 100.0],
        min_length=2,
        max_length=2,
        description="[left end, right end] of the scale; within 0..100.",
    )
    marker_start: Literal["hidden"] = Field(
        "hidden",
        description="No marker until the first click, so no start value can be logged "
        "as an answer.",
    )
    confirm: bool = Field(True, description="Require a confirm button press after rating.")


# ------------------------------------------------------------------------ presentation, rendering


class Practice(_Model):
    stimulus_set: Id
    stimulus: Id
    condition: Id


class VirtualReality(_Model):
    """Where the avatar stands in an immersive (``display: webxr``) session, and what runs
    when the participant's browser has no headset."""

    avatar_distance_m: float = Field(
        1.0,
        gt=0.2,
        le=10.0,
        description="From the seated participant's eyes (where they are when the avatar is "
        "placed) to the avatar's eyes, straight ahead, in metres.",
    )
    avatar_height_m: float = Field(
        0.0,
        ge=-1.0,
        le=1.0,
        description="The avatar's eyes above (+) or below (-) the participant's eyes (where "
        "they are when the avatar is placed: at the recentre step), in metres (0: eye to "
        "eye).",
    )
    fallback: Literal["none", "live3d"] = Field(
        "none",
        description="Without a headset: 'live3d' runs the session on the screen (the session "
        "file says which ran); 'none' asks for a headset and runs nothing.",
    )
    room: Literal["room", "floor", "none"] = Field(
        "room",
        description="What surrounds the participant in VR: 'room' a neutral room (floor, "
        "walls, ceiling), 'floor' a floor under the background colour, 'none' the background "
        "colour alone.",
    )
    fade_ms: int = Field(
        250,
        ge=0,
        le=2000,
        description="Each new screen or clip in VR fades in from black over this time, and "
        "a selected answer or a clip's end fades out to black over half of it (0: cut).",
    )
    recentre: bool = Field(
        True,
        description="On entering VR the participant looks straight ahead and confirms; the "
        "avatar is placed at their eye height and facing direction then (and again from the "
        "recentre button every panel shows). Off: placed at the first frame's pose.",
    )
    spatial_audio: bool = Field(
        True,
        description="The voice comes from the avatar's mouth (an HRTF panner that follows the "
        "head); off: the same sound in both ears, as in the video display.",
    )
    instructions: Localized | None = Field(
        None,
        description="The instructions as shown in VR (answers there are given with a "
        "controller or by gaze, not keys or mouse clicks); omitted: presentation.instructions.",
    )
    break_text: Localized | None = Field(
        None,
        description="The break text in VR; omitted: facelab's own, which names no key.",
    )
    end_text: Localized | None = Field(
        None,
        description="The end text in VR (the participant is then asked to remove the "
        "headset); omitted: presentation.end_text.",
    )


class AddedScreen(_Model):
    """A screen kind from an installed package shown in every trial (``facelab plugins``
    lists the installed kinds; the kind says where in the trial it goes)."""

    kind: str = Field(description="The screen kind's name, e.g. confidence.")
    options: dict[str, Any] = Field(
        default_factory=dict, description="The kind's own options (its documentation)."
    )


class Conversation(_Model):
    """A live conversation with a partner shown as the avatar (issue 53.4): a talker - the
    experimenter or a confederate, on the talker page ``/talk`` of ``facelab serve`` (online)
    or of the live server ``facelab run`` starts (in the lab) - speaks, the condition's method
    drives the avatar from the streamed voice, and the participant sees and hears it for
    ``minutes``; then the VAS ``items`` are asked about the partner. Each turn is recorded
    (audio, the track as shown, latencies) in the participant's folder."""

    condition: Id = Field(description="The condition whose method drives the partner's face.")
    minutes: float = Field(
        gt=0.0,
        le=120.0,
        description="How long the conversation lasts; online the talker can end it sooner.",
    )
    when: Literal["before", "after"] = Field(
        "before",
        description="Before the trials (after the instructions and practice) or after them.",
    )
    items: list[Id] | None = Field(
        None,
        description="The VAS items (ids from 'items') asked about the partner after the "
        "conversation; default all.",
    )
    text: Localized | None = Field(
        None, description="Shown with the avatar during the conversation; default facelab's."
    )


class Presentation(_Model):
    language: LangCode = Field("ja", description="Language of all participant-facing text.")
    items_layout: Literal["sequential", "together"] = "sequential"
    block_order: Literal["fixed", "latin_square"] = Field(
        "fixed",
        description="The order of the blocks in a session: fixed (the protocol's) or "
        "latin_square (a row of a balanced Latin square of the blocks chosen by the "
        "participant's number, so that across participants every block comes at every place "
        "and after every other equally often: learning and fatigue are spread over the "
        "blocks; participant ids must end in a number, e.g. P01).",
    )
    fullscreen: bool = True
    display: Literal["video", "live3d", "webxr"] = Field(
        "video",
        description="How clips are shown online: 'video' plays the rendered mp4; 'live3d' "
        "draws the avatar in the browser from each clip's animation track against the audio "
        "clock; 'webxr' does the same in an immersive VR session (see vr). The lab window "
        "always plays the video.",
    )
    vr: VirtualReality = Field(default_factory=VirtualReality)
    instructions: Localized | None = None
    practice: Practice | None = None
    added_screens: list[AddedScreen] = Field(
        default_factory=list,
        description="Screens of installed screen kinds added to every trial (after its "
        "responses or its clip, as the kind declares), logged as the kind's item.",
    )
    break_text: Localized | None = None
    end_text: Localized | None = None
    conversation: Conversation | None = Field(
        None,
        description="A live conversation with a partner shown as the avatar, then VAS items "
        "about the partner (online and in the lab window; logged as block 'conversation').",
    )
    ssq: list[Literal["before", "after"]] = Field(
        default_factory=list,
        description="The Simulator Sickness Questionnaire (Kennedy et al. 1993; 16 symptoms, "
        "none/slight/moderate/severe, one screen each) before the study's first screen after "
        "the welcome, after its last trial, or both: [before, after]. Logged as items "
        "ssq_<before|after>_<symptom>; facelab analyze scores it (ssq.csv).",
        json_schema_extra={"uniqueItems": True},
    )

    @field_validator("ssq")
    @classmethod
    def _ssq_once_each(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError("each of before and after may be named once")
        return value


class Camera(_Model):
    distance_m: float | None = Field(
        None,
        gt=0.1,
        le=20.0,
        description="Camera-to-face distance in metres; omitted: frames the head (0.65 m for "
        "the default head, scaled with the head's height for other avatars).",
    )
    fov_deg: float = Field(30.0, gt=5, lt=120, description="Vertical field of view.")
    height_m: float = Field(0.0, ge=-0.5, le=0.5, description="Camera height relative to the eyes.")
    target_m: list[float] | None = Field(
        None,
        min_length=3,
        max_length=3,
        description="The point the camera aims at [x, y, z] in the avatar's metres; omitted: "
        "the head's centre (from the head joint, the head mesh or the model's top).",
    )


class Rendering(_Model):
    width: int = Field(1280, ge=64, le=7680)
    height: int = Field(720, ge=64, le=4320)
    fps: int = Field(30, ge=1, le=240)
    avatar: Text = Field(
        "default",
        description="'default' or a .gltf/.glb/.vrm file (Ready Player Me, VRM 0.x/1.0, "
        "skinned glTF).",
    )
    camera: Camera = Field(default_factory=Camera)
    pad_s: float = Field(0.3, ge=0.0, le=5.0, description="Neutral face before and after speech.")
    msaa: Literal[1, 2, 4, 8] = Field(
        4,
        description="Multisample anti-aliasing samples per pixel: 4 (smooth edges) renders the "
        "default head at 720p30 in 0.72x real time on a 2-core CPU, 1 in 0.38x. Software "
        "OpenGL (llvmpipe) takes at most 4 (and gives 4 for 2); a larger value is refused "
        "when rendering starts.",
    )
    audio_sample_rate: int = Field(48000, ge=8000, le=192000)
    behaviour_seed: int = Field(
        1,
        ge=0,
        le=2**31 - 1,
        description="Seed of the behaviour planner; with the stimulus it seeds each layer, so "
        "conditions sharing a layer get the same random draws (yoked).",
    )
    background: list[float] = Field(
        default_factory=lambda: [0.5, 0.5, 0.5], min_length=3, max_length=3
    )
    audio_only_face: Literal["still", "none"] = Field(
        "still",
        description="What an audio_only condition's clips show: the avatar's still neutral "
        "face, or none (the background only).",
    )


# ------------------------------------------------------------------ simulation, reported results


#: a simulated condition effect: rating points added to the mean, a finite number
EffectPoints = Annotated[float, Field(allow_inf_nan=False)]
#: a weight in a simulated confusion row (rows are normalised: probabilities, percentages or
#: counts alike), finite and not negative
Weight = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class SimulationModel(_Model):
    """Simulated rating = clip(mean + effect + participant offset + interaction + noise, scale)."""

    mean: float = Field(50.0, ge=0, le=100, description="Mean rating with no condition effect.")
    participant_sd: float = Field(
        10.0, ge=0, le=100, description="SD of participant offsets (per item)."
    )
    interaction_sd: float = Field(
        4.0, ge=0, le=100, description="SD of participant x condition effects."
    )
    noise_sd: float = Field(12.0, ge=0, le=100, description="SD of rating-to-rating noise.")
    rt_median_s: float = Field(3.0, gt=0, le=60, description="Median response time (log-normal).")
    rt_log_sd: float = Field(0.35, ge=0, le=3, description="SD of log response time.")


class EffectOverride(_Model):
    """Condition effects for one item and/or stimulus set, replacing the defaults there."""

    item: Id | None = None
    stimulus_set: Id | None = None
    effects: dict[Id, EffectPoints]


class Observer(_Model):
    """A simulated psychometric observer for choice tasks: it picks the comparison with
    P = gamma + (1 - gamma - lapse) * F(level), F logistic with this midpoint and slope
    (gamma 1/2 when the task has a correct answer, else 0)."""

    midpoint: float = Field(0.5, allow_inf_nan=False, description="Level where F = 1/2.")
    slope: float = Field(10.0, gt=0, le=1e4, description="Logistic slope (per level unit).")
    lapse: float = Field(0.02, ge=0, le=0.5, description="Lapse rate.")
    midpoint_sd: float = Field(
        0.0, ge=0, allow_inf_nan=False,
        description="SD of participants' midpoints around 'midpoint'.",
    )


class Identifier(_Model):
    """A simulated identifier: the portrayed label is chosen with probability 'accuracy'
    (per condition: 'condition_accuracy'; or a row of 'confusion', per condition a row of
    'condition_confusion'), otherwise another label uniformly."""

    accuracy: float = Field(0.7, ge=0, le=1)
    condition_accuracy: dict[Id, Annotated[float, Field(ge=0, le=1)]] = Field(
        default_factory=dict,
        description="Condition id -> accuracy in that condition (replaces 'accuracy' there).",
    )
    confusion: dict[Id, dict[Id, Weight]] = Field(
        default_factory=dict,
        description="Portrayed label -> {chosen label: probability}; rows replace 'accuracy'.",
    )
    condition_confusion: dict[Id, dict[Id, dict[Id, Weight]]] = Field(
        default_factory=dict,
        description="Condition id -> {portrayed label: {chosen label: probability}}: how "
        "that condition is read (e.g. lip-reading one animation method); its rows replace "
        "'confusion' there.",
    )


class TimingObserver(_Model):
    """A simulated observer of audio-visual timing (one condition series). Simultaneity:
    P(in sync) = floor + (peak - floor) * exp(-(x - pss)^2 / (2 sigma^2)), width = 2 sqrt(2
    ln 2) sigma (full width at half the height above the floor). Temporal order: P(voice
    first) = lapse/2 + (1 - lapse) * Phi((pss - x) / sigma), width = 2 * 0.6745 sigma (25 %
    to 75 %). x: the offset in ms."""

    pss_ms: float = Field(0.0, ge=-1000, le=1000, description="Point of subjective simultaneity.")
    width_ms: float = Field(300.0, gt=0, le=4000, description="Width of the window (see above).")
    peak: float = Field(0.95, gt=0, le=1, description="Simultaneity: P(in sync) at the PSS.")
    floor: float = Field(
        0.0, ge=0, le=0.5, description="Simultaneity: P(in sync) far outside the window "
        "(guesses, a bias to say yes); at most 0.6 x peak."
    )
    lapse: float = Field(0.02, ge=0, le=0.5, description="Temporal order: lapse rate.")
    pss_sd_ms: float = Field(0.0, ge=0, allow_inf_nan=False, description="SD of participants' PSS.")
    width_sd_ms: float = Field(
        0.0, ge=0, allow_inf_nan=False, description="SD of participants' widths."
    )

    @model_validator(mode="after")
    def _floor_below_peak(self) -> TimingObserver:
        if self.floor > 0.6 * self.peak:
            raise ValueError(f"floor ({self.floor:g}) must be at most 0.6 x peak "
                             f"({0.6 * self.peak:g}), the most the window fit allows")  # fmt: skip
        return self


class SrtListener(_Model):
    """A simulated listener of speech in noise (one condition series): a right answer with
    P = guess + (1 - guess - lapse) * logistic(...) through 1/2 at ``srt_db`` with
    ``slope`` per dB there (guess: 1/k for k labels)."""

    srt_db: float = Field(ge=-40, le=40, description="SNR of 50 % right answers.")
    slope: float = Field(0.1, gt=0, le=1, description="Proportion correct per dB at the SRT.")
    lapse: float = Field(0.02, ge=0, le=0.1, description="Lapse rate (the fit's bound).")
    srt_sd_db: float = Field(
        0.0, ge=0, le=20, description="SD of participants' SRTs (one draw per participant, "
        "shared by the series: a good listener is good in every series)."
    )


class Simulation(_Model):
    """How ``facelab simulate`` generates answers; never presented as data."""

    model: SimulationModel = Field(default_factory=SimulationModel)
    effects: dict[Id, EffectPoints] = Field(
        default_factory=dict, description="Condition id -> points added to the mean (default 0)."
    )
    overrides: list[EffectOverride] = Field(default_factory=list)
    observer: Observer = Field(default_factory=Observer)
    identifier: Identifier = Field(default_factory=Identifier)
    srt: dict[Id, SrtListener] = Field(
        default_factory=dict,
        description="Condition series -> how a simulated participant hears words in noise "
        "(identify tasks with answers on conditions with noise); other series: 'identifier'.",
    )
    timing: dict[Id, TimingObserver] = Field(
        default_factory=dict,
        description="Condition series -> how a simulated participant judges its timing "
        "(tasks with 'timing'); series not named here: the default observer.",
    )


class ReportedPair(_Model):
    a: Id
    b: Id
    p: float = Field(ge=0, le=1)


class ReportedTest(_Model):
    item: Id
    stimulus_set: Id
    anova_p: float = Field(ge=0, le=1)
    pairs: list[ReportedPair] = Field(
        default_factory=list, description="Pairs reported as different; others were not."
    )


class ReportedResults(_Model):
    """Statistics a publication reported for this design, shown beside facelab's."""

    source: Text
    procedure: Text
    tests: list[ReportedTest] = Field(min_length=1)


# ------------------------------------------------------------------------- stimulus checks


class ArticulationRule(_Model):
    """A mouth relation the rendered clips must show, as the face tracker measures it: the
    median ``measure`` at the peaks of ``vowel`` in ``condition`` is at least ``at_least``
    times the same in ``relative_to``."""

    measure: Literal["aperture", "width"] = Field(
        description="Inner-lip aperture or mouth width, each over the face height."
    )
    vowel: Literal["a", "i", "u", "e", "o"]
    condition: Id
    relative_to: Id
    at_least: float = Field(gt=0, le=100, description="e.g. 1.3: 30 % more than relative_to.")


class AnalysisOptions(_Model):
    """How ``facelab analyze`` treats the study beyond its defaults."""

    reference: Id | None = Field(
        None,
        description="A condition whose motion the others are measured against (e.g. a "
        "captured human): objective.csv holds every other condition's distance to it per "
        "stimulus (mouth channels, timing lag, tracked lip aperture and width), related to "
        "the ratings in the report.",
    )


#: the stimulus checks by name (``facelab check``; ``checks.accept`` and --accept-check)
CHECK_NAMES = (
    "avatar_audit",
    "conditions_differ",
    "articulation",
    "face_visible",
    "av_sync",
    "levels",
    "modality",
    "noise",
    "track_source",
)


def accept_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be accepted (``--accept-check`` and ``checks.accept``: a check's
    name, or ``NAME:CLIP`` for one clip's failures), or None."""
    check, colon, clip = name.partition(":")
    if check in CHECK_NAMES and not (colon and not clip.strip()):
        return None
    return (f"unknown check {name!r}; checks: {', '.join(CHECK_NAMES)} (each alone, or "
            "NAME:CLIP for one clip)")  # fmt: skip


class StimulusChecks(_Model):
    """What ``facelab check`` (and every render) holds the clips to beyond its defaults."""

    equal_conditions: list[list[Id]] = Field(
        default_factory=list,
        description="Groups of conditions meant to render alike (e.g. a repeated control); "
        "any other two conditions must differ on the face.",
    )
    articulation: list[ArticulationRule] = Field(
        default_factory=list,
        description="Rules between conditions, checked on stimuli with expected_vowels.",
    )
    vowel_rules: bool = Field(
        True,
        description="The default Japanese vowel rules on stimuli with expected_vowels: "
        "a the largest aperture, u the smallest, i the widest mouth.",
    )
    accept: list[str] = Field(
        default_factory=list,
        description="Checks whose failures are accepted (recorded, not an error), by name: "
        f"{', '.join(CHECK_NAMES)}; NAME:CLIP accepts one clip's only "
        "(e.g. track_source:s__r01__standard).",
    )


# --------------------------------------------------------------------------- the protocol


class Protocol(_Model):
    """A whole study. Build one with :func:`load_protocol`, which also checks references."""

    schema_version: Literal[1] = SCHEMA_VERSION
    study: Study
    seed: int = Field(ge=0, lt=2**63, description="Study seed; participant seeds derive from it.")
    conditions: list[Condition] = Field(min_length=1)
    stimulus_sets: list[StimulusSet] = Field(min_length=1)
    blocks: list[Block] = Field(min_length=1)
    items: list[VasItem] = Field(
        default_factory=list, description="The VAS items; needed when a block has no task."
    )
    tasks: list[Task] = Field(
        default_factory=list, description="Forced-choice and identification tasks of blocks."
    )
    presentation: Presentation = Field(default_factory=Presentation)
    rendering: Rendering = Field(default_factory=Rendering)
    simulation: Simulation = Field(default_factory=Simulation)
    checks: StimulusChecks = Field(
        default_factory=StimulusChecks,
        description="The stimulus checks' protocol rules (facelab check).",
    )
    analysis: AnalysisOptions = Field(default_factory=AnalysisOptions)
    reported_results: ReportedResults | None = None

    # -- convenience lookups (the loader guarantees the ids are unique)
    def condition(self, condition_id: str) -> Condition:
        return next(c for c in self.conditions if c.id == condition_id)

    def stimulus_set(self, set_id: str) -> StimulusSet:
        return next(s for s in self.stimulus_sets if s.id == set_id)

    def task(self, task_id: str) -> AnyTask:
        return next(t for t in self.tasks if t.id == task_id)

    def block_task(self, block: Block) -> AnyTask | None:
        return None if block.task is None else self.task(block.task)

    def offset_twins(self) -> list[list[str]]:
        """Groups of condition ids alike but for their sound (``audio_offset_ms``,
        ``noise``): their clips show one picture (rendered once, the others re-muxed with
        their own sound)."""
        groups: dict[str, list[str]] = {}
        for c in self.conditions:
            alike = c.model_dump(exclude={"id", "label", "audio_offset_ms", "noise", "level"})
            groups.setdefault(json.dumps(alike, sort_keys=True, default=str), []).append(c.id)
        sound = {c.id: (c.audio_offset_ms, repr(c.noise)) for c in self.conditions}
        return [ids for ids in groups.values() if len({sound[i] for i in ids}) > 1]

    def block_conditions(self, block: Block) -> list[str]:
        if block.conditions:
            return list(block.conditions)
        task = next((t for t in self.tasks if t.id == block.task), None)
        skip = task.standard if isinstance(task, ChoiceTask) else None
        return [c.id for c in self.conditions if c.id != skip]


def json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of the protocol format."""
    schema = Protocol.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "facelab protocol"
    return schema


def schema_json_text() -> str:
    """The schema as committed in protocols/schema/protocol.schema.json."""
    return json.dumps(json_schema(), indent=2, ensure_ascii=False, sort_keys=True) + "\n"
