"""A session is a timeline of screens: jsPsych's timeline and plugins, in Python. Pure.

:func:`compile_timeline` turns a protocol and a participant's trial list into the screens a
participant sees, in order: a welcome screen (for the experimenter to check the id), the
sickness questionnaire if the protocol asks for it before (``presentation.ssq``),
instructions, a practice trial (never logged), then per trial its clip screen and its
response screens, breaks after blocks that ask for one, the questionnaire if asked for after,
and an end screen.

Each screen is a small frozen class with its parameters, the responses it collects
(:meth:`Screen.response_keys`: ``(trial_index, item)`` pairs) and the log rows it produces from them
(:meth:`ResponseScreen.rows`). Three walkers use the same timeline:

* the lab runner (:mod:`facelab.experiment.runner`) presents each screen in a PsychoPy window;
* :mod:`facelab.experiment.simulate` answers each screen with a simulated responder;
* an online session presents it in a browser (later).

A screen kind is one class registered once (:func:`screen_kind`) that owns everything about
it: its parameters, the responses it collects, its JSON for the browser (:meth:`Screen.browser`,
matched by one jsPsych plugin with typed parameters in ``online/web/static/plugins.js``), a
posted answer checked and turned into a log row (:meth:`ResponseScreen.answer`,
:meth:`ResponseScreen.row`), and how a presenter shows it (:meth:`Screen.present`: by default
the presenter's method named after the kind, so the lab window and the simulated participant
look screens up by ``kind``). It then inherits logging, resume and simulation.

Resume (:func:`remaining`): a response screen whose responses are all logged is skipped; a
trial with any response missing shows its clip again (the participant must see what they
rate), then only the missing response screens, in the original order. Instructions and the
practice trial are not repeated; a "continuing" screen is shown instead.
"""

from __future__ import annotations

import math
import re
import unicodedata
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

from facelab import sickness_questionnaire as ssq
from facelab.design import PENDING, Trial
from facelab.protocol import (
    AnyTask,
    ChoiceTask,
    IdentifyTask,
    MatrixTask,
    Protocol,
    TypedTask,
    VasItem,
)
from facelab.sessionlog import NA, SessionContext, response_row

if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "SCREEN_KINDS",
    "UI_TEXT",
    "AdaptiveTrial",
    "AnswerError",
    "BrowserContext",
    "ChoiceAnswer",
    "ChoiceScreen",
    "ClipKey",
    "ClipPairScreen",
    "ClipScreen",
    "ConversationAnswer",
    "ConversationScreen",
    "IdentifyAnswer",
    "IdentifyScreen",
    "MatrixScreen",
    "PairPlayback",
    "Playback",
    "ResponseScreen",
    "Screen",
    "SsqAnswer",
    "SsqScreen",
    "TaskScreen",
    "TextScreen",
    "TypedAnswer",
    "TypedScreen",
    "VasAnswer",
    "VasScreen",
    "compile_timeline",
    "conversation_screens",
    "localized",
    "needed_clips",
    "number",
    "remaining",
    "screen_kind",
    "ssq_screens",
    "trial_screens",
    "vr_texts",
    "vr_wording_notes",
]

#: (stimulus set, stimulus, condition): one rendered clip.
ClipKey = tuple[str, str, str]
S = TypeVar("S", bound="Screen")

#: Texts of the session screens by language (the protocol's own texts replace some).
UI_TEXT: dict[str, dict[str, str]] = {
    "ja": {
        "welcome": "参加者 {pid}（セッション {ses}）\n\nスペースキーで開始します。",
        "confirm": "決定",
        "practice": "練習試行です。",
        "quit": "実験を中断しますか？  y: 中断 / n: 続ける",
        "resume": "中断したところから再開します。\n\nスペースキーで続けます。",
        "resume_vr": "中断したところから再開します。",
        "next": "スペースキーで次へ",
        "break": "休憩です。準備ができたらスペースキーを押してください。",
        "break_vr": "休憩です。準備ができたら「次へ」を選んでください。",
        "end": "終了です。ありがとうございました。",
        "interval": "{n} つ目",
        "left": "左",
        "right": "右",
        "choice_keys": "1 か 2 のキー、またはクリックで答えてください",
        "label_keys": "数字キー、またはクリックで答えてください",
        "typed_keys": "聞こえたとおりに入力し、Enter キーか「決定」で答えてください"
        "（聞き取れなければ空欄のまま）",
        "matrix_keys": "各列から聞こえた言葉を一つずつクリックし、「決定」で答えてください"
        "（分からないときは推測で）",
        "matrix_column": "{n}列目",
        "conversation": "画面の相手と話してください。",
        "partner": "いま話した相手について答えてください。",
    },
    "en": {
        "welcome": "Participant {pid} (session {ses})\n\nPress space to start.",
        "confirm": "Confirm",
        "practice": "Practice trial.",
        "quit": "Quit the session?  y: quit / n: continue",
        "resume": "Continuing where the session stopped.\n\nPress space.",
        "resume_vr": "Continuing where the session stopped.",
        "next": "Press space to continue",
        "break": "Take a break. Press space when you are ready.",
        "break_vr": "Take a break. Select Next when you are ready.",
        "end": "This is the end. Thank you.",
        "interval": "Clip {n}",
        "left": "Left",
        "right": "Right",
        "choice_keys": "Press 1 or 2, or click",
        "label_keys": "Press a number key, or click",
        "typed_keys": "Type what you heard, then press Enter or click Confirm (leave it "
        "empty if you heard nothing)",
        "matrix_keys": "Click the word you heard in each column, then Confirm (guess when "
        "unsure)",
        "matrix_column": "Column {n}",
        "conversation": "Talk with the partner on the screen.",
        "partner": "Please answer about the partner you just talked with.",
    },
}


def localized(text: dict[str, str] | None, lang: str, default: str = "") -> str:
    """The text in ``lang`` (the protocol guarantees it for participant-facing texts)."""
    if not text:
        return default
    return text.get(lang) or next(iter(text.values()))


def ui(lang: str) -> dict[str, str]:
    return UI_TEXT.get(lang, UI_TEXT["en"])


# --------------------------------------------------------------------------- screens


class AnswerError(ValueError):
    """An answer (posted by a browser) that does not fit its screen; the message names the
    field."""


def number(payload: Mapping[str, Any], key: str, *, lo: float, hi: float) -> float:
    """``payload[key]`` as a finite number in [lo, hi], else :class:`AnswerError`."""
    value = payload.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise AnswerError(f"{key}: expected a number, got {value!r}")
    if not lo <= float(value) <= hi:
        raise AnswerError(f"{key}: {value} is outside {lo}..{hi}")
    return float(value)


@dataclass(frozen=True)
class BrowserContext:
    """What a screen's browser JSON may use: the session's language and texts, the clips as
    the browser fetches them, and the trials whose clip was already shown (a resume)."""

    lang: str
    clip_json: Callable[[ClipKey], dict[str, Any]]
    shown_before: frozenset[int] = frozenset()
    # the practice trial's clip as the browser fetches it (online: a copy of its own, so it
    # cannot be matched to the main trial showing the same clip); default clip_json
    practice_json: Callable[[ClipKey], dict[str, Any]] | None = None
    # display webxr: the texts of text screens (by role) as VR shows them (:func:`vr_texts`)
    vr_texts: Mapping[str, str] = field(default_factory=dict)

    @property
    def texts(self) -> dict[str, str]:
        return ui(self.lang)


#: kind -> screen class; every kind is registered once (:func:`screen_kind`)
SCREEN_KINDS: dict[str, type[Screen]] = {}


def screen_kind(cls: type[S]) -> type[S]:
    """Class decorator: register a screen class under its ``kind``."""
    if cls.kind in SCREEN_KINDS and SCREEN_KINDS[cls.kind] is not cls:
        raise ValueError(f"screen kind {cls.kind!r} is registered already")
    SCREEN_KINDS[cls.kind] = cls
    return cls


@dataclass(frozen=True)
class Screen:
    """A screen of the timeline. ``trial`` is None for screens outside the trials."""

    kind: ClassVar[str] = "screen"
    #: the jsPsych plugin of a kind added to facelab: a JS file that defines it and sets
    #: ``FacelabPlugins[kind]`` (served at /plugins/<kind>.js and loaded by the session page
    #: when a timeline shows the kind); None for the built-in kinds, which are in plugins.js
    plugin_js: ClassVar[Path | None] = None

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        """The responses this screen collects (none for passive screens)."""
        return ()

    def present(self, presenter: Any) -> Any:
        """Show the screen with ``presenter`` (the lab window, a simulated participant): its
        method named after the kind. A kind whose presenters lack such a method overrides
        this."""
        method = getattr(presenter, self.kind, None)
        if method is None:
            raise TypeError(f"{type(presenter).__name__} cannot present screen kind {self.kind!r}")
        return method(self)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        """The screen as JSON for its jsPsych plugin: ``kind`` and the plugin's parameters."""
        raise TypeError(f"screen kind {self.kind!r} has no browser form")

    @property
    def trial_index(self) -> int | None:
        trial = getattr(self, "trial", None)
        return None if trial is None else trial.trial_index


@screen_kind
@dataclass(frozen=True)
class TextScreen(Screen):
    """A text the participant reads and dismisses with the space bar (online: a button; in
    VR: a panel's button, and the text as :func:`vr_texts` words it)."""

    kind: ClassVar[str] = "text"
    role: str  # welcome | instructions | practice | resume | partner | break | end
    text: str

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {"kind": self.kind, "role": self.role, "text": self.text,
                "vr_text": ctx.vr_texts.get(self.role, "")}  # fmt: skip


@screen_kind
@dataclass(frozen=True)
class ClipScreen(Screen):
    """One rendered clip, with sound. Produces a :class:`Playback` record."""

    kind: ClassVar[str] = "clip"
    trial: Trial | None
    clip: ClipKey
    practice: bool = False
    interval: int | None = None  # 1 or 2 in a forced choice (announced before the clip)
    gap_s: float = 0.0  # blank before the clip (between the two clips of a forced choice)

    def clips(self) -> tuple[ClipKey, ...]:
        """The clips this screen shows."""
        return (self.clip,)

    def _shown(self, ctx: BrowserContext) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "trial_index": self.trial_index,
            "practice": self.practice,
            "replay": self.trial_index in ctx.shown_before,
        }

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        fetch = ctx.practice_json if self.practice and ctx.practice_json else ctx.clip_json
        return self._shown(ctx) | {
            **fetch(self.clip),
            "interval": self.interval,
            "announce": ctx.texts["interval"].format(n=self.interval) if self.interval else "",
            "gap_s": self.gap_s,
        }


@screen_kind
@dataclass(frozen=True)
class ClipPairScreen(ClipScreen):
    """Two clips at once, side by side (a side-by-side forced choice): ``clip`` on the left,
    ``right`` on the right, started together; the sound is that of the clip on side
    ``sound`` (1 left, 2 right), the other plays muted. Produces a :class:`PairPlayback`."""

    kind: ClassVar[str] = "clip_pair"
    right: ClipKey = ("", "", "")
    sound: int = 1

    def clips(self) -> tuple[ClipKey, ...]:
        return (self.clip, self.right)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return self._shown(ctx) | {
            "clips": [ctx.clip_json(c) for c in self.clips()],
            "sound": self.sound,
        }


@dataclass(frozen=True)
class Playback:
    """How a clip was shown: onset (s, session clock), frames dropped, every flip."""

    onset: float
    dropped: int
    frames_expected: int = 0
    flip_times: tuple[float, ...] = ()
    frames_shown: tuple[int, ...] = ()

    def record(self, *, trial_index: int | None, clip: str, replay: bool) -> dict[str, Any]:
        """The line written to ``..._playback.jsonl``."""
        return {
            "trial_index": trial_index,
            "clip": clip,
            "replay": replay,
            "onset": self.onset,
            "frames_expected": self.frames_expected,
            "dropped": self.dropped,
            "flip_times": list(self.flip_times),
            "frames_shown": list(self.frames_shown),
        }

    def joined(self, other: Playback) -> Playback:
        """The playback of a trial with two clips (in sequence or side by side): this one's
        onset, the frames expected and dropped in both."""
        return Playback(
            onset=self.onset,
            dropped=self.dropped + other.dropped,
            frames_expected=self.frames_expected + other.frames_expected,
        )


@dataclass(frozen=True)
class PairPlayback:
    """How the two clips of a :class:`ClipPairScreen` were shown, each with its own record."""

    left: Playback
    right: Playback

    def combined(self) -> Playback:
        """The trial's playback for its log rows (both clips start on the same flip)."""
        return self.left.joined(self.right)


@dataclass(frozen=True)
class ResponseScreen(Screen):
    """A screen that collects responses; each becomes one log row when the screen ends."""

    trial: Trial | None
    practice: bool = False
    level: float | None = None  # the trial's condition on a graded dimension

    def answer(self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str) -> Any:
        """The answer to ``item`` a browser posted (its kind's fields checked), as the
        presenters give it; :class:`AnswerError` naming the field when it does not fit."""
        raise AnswerError(f"screen {self.kind} takes no posted answers")

    def row(
        self, item: str, answer: Any, *, context: SessionContext, playback: Playback | None
    ) -> dict[str, Any]:
        """The log row of one answer to ``item``."""
        raise NotImplementedError(f"{type(self).__name__} does not define row()")

    def posted(self, answer: Any) -> dict[str, Any]:
        """The answer-specific fields a browser posts for ``answer`` (the inverse of
        :meth:`answer`): what simulated browser participants send."""
        raise NotImplementedError(f"{type(self).__name__} does not define posted()")

    def answer_item(self, answer: Any) -> str:
        """The item an answer is to (the task's one item, or the answer's own)."""
        return str(getattr(answer, "item", None) or self.response_keys()[0][1])

    def rows(
        self, answers: Sequence[Any], *, context: SessionContext, playback: Playback | None
    ) -> list[dict[str, Any]]:
        """The log rows of a screen's answers, in the order of its items (none for the
        practice trial)."""
        if not self.response_keys():
            return []
        by_item = {self.answer_item(a): a for a in answers}
        return [
            self.row(item, by_item[item], context=context, playback=playback)
            for _, item in self.response_keys()
        ]

    def _row(
        self, *, context: SessionContext, playback: Playback | None, item: str, **answer: Any
    ) -> dict[str, Any]:
        """One log row of this screen's trial: the trial, clip and level columns filled in."""
        return response_row(
            context=context,
            trial=self.trial,
            item=item,
            screen=self.kind,
            clip_onset=None if playback is None else playback.onset,
            clip_frames_dropped=None if playback is None else playback.dropped,
            level=self.level,
            **answer,
        )


@dataclass(frozen=True)
class VasAnswer:
    """A confirmed VAS response."""

    item: str
    rating: float
    rt_s: float
    timestamp: str
    rating_start: float | None = None


@screen_kind
@dataclass(frozen=True)
class VasScreen(ResponseScreen):
    """One VAS item (``items_layout: sequential``) or several on one screen (``together``)."""

    kind: ClassVar[str] = "vas"
    items: tuple[VasItem, ...] = ()

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        if self.practice or self.trial is None:
            return ()
        return tuple((self.trial.trial_index, item.id) for item in self.items)

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> VasAnswer:
        (vas_item,) = [it for it in self.items if it.id == item]
        lo, hi = sorted(vas_item.range)
        rating = number(posted, "rating", lo=lo, hi=hi)
        return VasAnswer(item=item, rating=rating, rt_s=rt_s, timestamp=timestamp)

    def posted(self, answer: VasAnswer) -> dict[str, Any]:
        return {"rating": answer.rating}

    def row(
        self, item: str, answer: VasAnswer, *, context: SessionContext, playback: Playback | None
    ) -> dict[str, Any]:
        return self._row(
            context=context,
            playback=playback,
            item=item,
            rating=answer.rating,
            rating_start=answer.rating_start,
            rt_s=answer.rt_s,
            timestamp=answer.timestamp,
        )

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "trial_index": self.trial_index,
            "practice": self.practice,
            "confirm": ctx.texts["confirm"],
            "items": [
                {
                    "id": it.id,
                    "question": localized(it.question, ctx.lang),
                    "left": localized(it.left_anchor, ctx.lang),
                    "right": localized(it.right_anchor, ctx.lang),
                    "range": list(it.range),
                }
                for it in self.items
            ],
        }


@dataclass(frozen=True)
class TaskScreen(ResponseScreen):
    """A screen that collects a task's one answer per trial (forced choice, identification)."""

    task: AnyTask | None = None

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        if self.practice or self.trial is None or self.task is None:
            return ()
        return ((self.trial.trial_index, self.task.id),)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        assert self.task is not None
        return {
            "kind": self.kind,
            "trial_index": self.trial_index,
            "practice": self.practice,
            "item": self.task.id,
            "question": localized(self.task.question, ctx.lang),
        }


@dataclass(frozen=True)
class ChoiceAnswer:
    """A forced choice: ``choice`` is the interval picked, 1 (first) or 2 (second)."""

    choice: int
    rt_s: float
    timestamp: str


@screen_kind
@dataclass(frozen=True)
class ChoiceScreen(TaskScreen):
    """Which of the two clips? The comparison was in interval (or on side) ``trial.position``;
    answer 1 is the first (left) clip, 2 the second (right)."""

    kind: ClassVar[str] = "choice_2afc"
    task: ChoiceTask | None = None

    def options(self, lang: str) -> list[str]:
        """The two answers' texts: "Clip 1"/"Clip 2", or "Left"/"Right" side by side."""
        texts = ui(lang)
        if self.task is not None and self.task.layout == "side_by_side":
            return [texts["left"], texts["right"]]
        return [texts["interval"].format(n=n) for n in (1, 2)]

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return super().browser(ctx) | {"options": self.options(ctx.lang)}

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> ChoiceAnswer:
        choice = posted.get("choice")
        if choice not in (1, 2) or isinstance(choice, bool):
            raise AnswerError(f"choice: expected 1 or 2, got {choice!r}")
        return ChoiceAnswer(choice=int(choice), rt_s=rt_s, timestamp=timestamp)

    def posted(self, answer: ChoiceAnswer) -> dict[str, Any]:
        return {"choice": answer.choice}

    def row(
        self, item: str, answer: ChoiceAnswer, *, context: SessionContext, playback: Playback | None
    ) -> dict[str, Any]:
        assert self.trial is not None and self.task is not None
        chose_comparison = answer.choice == self.trial.position
        return self._row(
            context=context,
            playback=playback,
            item=item,
            rt_s=answer.rt_s,
            timestamp=answer.timestamp,
            response=self.trial.condition if chose_comparison else self.trial.standard,
            correct=int(chose_comparison) if self.task.correct == "comparison" else None,
        )


@dataclass(frozen=True)
class IdentifyAnswer:
    """An identification: the id of the label chosen."""

    label: str
    rt_s: float
    timestamp: str


@screen_kind
@dataclass(frozen=True)
class IdentifyScreen(TaskScreen):
    """Which label fits the clip? Correct when the task names the condition's label."""

    kind: ClassVar[str] = "identify"
    task: IdentifyTask | None = None

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        assert self.task is not None
        labels = [{"id": lb.id, "text": localized(lb.text, ctx.lang)} for lb in self.task.labels]
        return super().browser(ctx) | {"labels": labels}

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> IdentifyAnswer:
        assert self.task is not None
        label = posted.get("label")
        ids = [lb.id for lb in self.task.labels]
        if label not in ids:
            raise AnswerError(f"label: expected one of {ids}, got {label!r}")
        return IdentifyAnswer(label=str(label), rt_s=rt_s, timestamp=timestamp)

    def posted(self, answer: IdentifyAnswer) -> dict[str, Any]:
        return {"label": answer.label}

    def row(
        self,
        item: str,
        answer: IdentifyAnswer,
        *,
        context: SessionContext,
        playback: Playback | None,
    ) -> dict[str, Any]:
        assert self.trial is not None and self.task is not None
        target = self.task.target(condition=self.trial.condition, stimulus=self.trial.stimulus)
        return self._row(
            context=context,
            playback=playback,
            item=item,
            rt_s=answer.rt_s,
            timestamp=answer.timestamp,
            response=answer.label,
            correct=None if target is None else int(answer.label == target),
        )


@dataclass(frozen=True)
class TypedAnswer:
    """A typed answer: the text as typed (whitespace runs made one space, Unicode NFC)."""

    text: str
    rt_s: float
    timestamp: str


def typed_text(raw: str) -> str:
    """A typed answer as the log stores it: NFC, control and format characters (e.g. a
    zero-width space) dropped, every run of whitespace (tabs, newlines, ideographic spaces)
    one space, no space at either end."""
    text = unicodedata.normalize("NFC", raw)
    text = "".join(" " if ch.isspace() else ch for ch in text
                   if ch.isspace() or unicodedata.category(ch) not in ("Cc", "Cf"))  # fmt: skip
    return " ".join(text.split())


def typed_score(*, said: str, text: str, task: TypedTask, keywords: Sequence[str] | None) -> float:
    """The share of ``said``'s scoring units ``text`` reproduces, as pronounced (OpenJTalk's
    reading, :mod:`facelab.analysis.typed_scoring`)."""
    from facelab.analysis.typed_scoring import score_typed
    from facelab.japanese_reading import morae, pronunciation

    if not text:
        return 0.0
    score = score_typed(said, text, reader=pronunciation, split=morae, keywords=keywords,
                        tolerant=task.tolerant)  # fmt: skip
    value = score.keyword_score if task.scoring == "keywords" else score.mora_score
    return 0.0 if math.isnan(value) else round(float(value), 6)


@screen_kind
@dataclass(frozen=True)
class TypedScreen(TaskScreen):
    """Type what was said: a text field and a confirm button (Return confirms). ``said`` and
    ``keywords`` are what the answer is scored against (the stimulus' text, or the task's)."""

    kind: ClassVar[str] = "typed"
    task: TypedTask | None = None
    said: str = ""
    keywords: tuple[str, ...] | None = None

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        assert self.task is not None
        return super().browser(ctx) | {
            "max_length": self.task.max_length,
            "confirm": ctx.texts["confirm"],
            "hint": ctx.texts["typed_keys"],
        }

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> TypedAnswer:
        assert self.task is not None
        raw = posted.get("text")
        if not isinstance(raw, str):
            raise AnswerError(f"text: expected the typed text, got {raw!r}")
        text = typed_text(raw)
        if text == NA:
            raise AnswerError(f"text: {NA!r} is how the log marks a missing value, not an answer")
        if len(text) > self.task.max_length:
            raise AnswerError(f"text: {len(text)} characters, at most {self.task.max_length}")
        return TypedAnswer(text=text, rt_s=rt_s, timestamp=timestamp)

    def posted(self, answer: TypedAnswer) -> dict[str, Any]:
        return {"text": answer.text}

    def score(self, text: str) -> float:
        """The share of the scoring units ``text`` reproduces."""
        assert self.task is not None
        return typed_score(said=self.said, text=text, task=self.task, keywords=self.keywords)

    def row(
        self, item: str, answer: TypedAnswer, *, context: SessionContext, playback: Playback | None
    ) -> dict[str, Any]:
        score = self.score(answer.text)
        return self._row(
            context=context,
            playback=playback,
            item=item,
            rt_s=answer.rt_s,
            timestamp=answer.timestamp,
            response=answer.text or None,
            correct=int(score >= 1.0),
            score=score,
        )


@screen_kind
@dataclass(frozen=True)
class MatrixScreen(TypedScreen):
    """Pick what was said from a word matrix: one word in each column, then confirm. The
    answer is the picks joined by spaces (a :class:`TypedAnswer`); ``said`` is the words
    said, joined likewise, and the score the share of columns picked right."""

    kind: ClassVar[str] = "matrix"
    task: MatrixTask | None = None  # type: ignore[assignment]

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        assert self.task is not None
        return TaskScreen.browser(self, ctx) | {
            "columns": [list(c) for c in self.task.columns],
            # each column's name for screen readers (a group of buttons)
            "column_labels": [
                ctx.texts["matrix_column"].format(n=i + 1) for i in range(len(self.task.columns))
            ],
            "confirm": ctx.texts["confirm"],
            "hint": ctx.texts["matrix_keys"],
        }

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> TypedAnswer:
        assert self.task is not None
        words = posted.get("words")
        n = len(self.task.columns)
        if not isinstance(words, list) or len(words) != n:
            raise AnswerError(f"words: expected a list of {n} words, one from each column, "
                              f"got {words!r}")  # fmt: skip
        for i, (word, column) in enumerate(zip(words, self.task.columns, strict=True)):
            if word not in column:
                raise AnswerError(f"words[{i}]: {word!r} is not in column {i + 1}")
        return TypedAnswer(text=" ".join(words), rt_s=rt_s, timestamp=timestamp)

    def posted(self, answer: TypedAnswer) -> dict[str, Any]:
        return {"words": answer.text.split(" ") if answer.text else []}

    def score(self, text: str) -> float:
        """The share of the columns whose pick is the word said there."""
        said, picked = self.said.split(" "), text.split(" ")
        if not said or len(picked) != len(said):
            return 0.0
        return round(sum(a == b for a, b in zip(said, picked, strict=True)) / len(said), 6)


@screen_kind
@dataclass(frozen=True)
class AdaptiveTrial(ResponseScreen):
    """A staircase trial before its level is known: the walker asks the block's staircase for
    the condition, then shows :meth:`expand`'s screens. Collects the task's one response."""

    kind: ClassVar[str] = "adaptive"
    protocol: Protocol | None = field(default=None, compare=False, repr=False)

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        assert self.trial is not None and self.protocol is not None
        block = next(b for b in self.protocol.blocks if b.id == self.trial.block)
        return ((self.trial.trial_index, str(block.task)),)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        """A placeholder: the browser asks for the trial's screens once the answers before it
        are stored (the staircase rule runs on the server)."""
        assert self.trial is not None
        return {"kind": self.kind, "trial_index": self.trial_index, "block": self.trial.block}

    def expand(self, condition: str) -> list[Screen]:
        """The screens of this trial at ``condition``."""
        assert self.trial is not None and self.protocol is not None
        return trial_screens(self.protocol, replace(self.trial, condition=condition))


# --------------------------------------------------------------------------- compiling


@dataclass(frozen=True)
class SsqAnswer:
    """One symptom's answer, 0-3 (the log row's response)."""

    value: int
    rt_s: float
    timestamp: str


@screen_kind
@dataclass(frozen=True)
class SsqScreen(ResponseScreen):
    """One symptom of the Simulator Sickness Questionnaire (``presentation.ssq``;
    :mod:`facelab.sickness_questionnaire`): the symptom and its four answers as buttons (the
    lab window's numbered buttons, the browser's generic buttons plugin, a VR panel), logged
    as item ``ssq_<moment>_<symptom>`` with the answer 0-3 as the response. Its row's trial is
    the questionnaire's own (trial index 0, block ``ssq``, condition the moment, stimulus the
    symptom), outside the participant's design."""

    kind: ClassVar[str] = "ssq"
    moment: str = "before"
    symptom: str = ""

    def item_id(self) -> str:
        return ssq.item_id(moment=self.moment, symptom=self.symptom)

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        return ((0, self.item_id()),)

    def question(self, lang: str) -> str:
        words = next(s.text for s in ssq.SYMPTOMS if s.id == self.symptom)
        if lang == "ja":
            return f"【{words['ja']}】{ssq.QUESTION['ja']}"
        return f"{words['en']}: {ssq.QUESTION['en'].lower()}"

    def choices(self, lang: str) -> list[tuple[int, str]]:
        return [(v, text.get(lang, text["en"])) for v, text in ssq.ANSWERS]

    def simulate(self, rng: np.random.Generator) -> int:
        """A simulated answer: mostly no symptom, a little more after the study than before."""
        p = (0.75, 0.2, 0.05, 0.0) if self.moment == "before" else (0.55, 0.3, 0.12, 0.03)
        return int(rng.choice(4, p=p))

    def present(self, presenter: Any) -> Any:
        """Answered as a screen of buttons: the lab window through :meth:`lab`, a simulated
        participant through :meth:`simulate` (their ``added_screen``)."""
        return presenter.added_screen(self)

    def lab(self, window: Any) -> tuple[int, float]:
        return window.buttons(self)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {
            "kind": self.kind, "trial_index": 0, "item": self.item_id(), "practice": False,
            "widget": "buttons", "question": self.question(ctx.lang),
            "choices": [{"value": v, "label": label} for v, label in self.choices(ctx.lang)],
        }  # fmt: skip

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> SsqAnswer:
        value = posted.get("value")
        if isinstance(value, bool) or value not in (0, 1, 2, 3):
            raise AnswerError(f"value: expected 0, 1, 2 or 3, got {value!r}")
        return SsqAnswer(int(value), rt_s, timestamp)

    def posted(self, answer: Any) -> dict[str, Any]:
        return {"value": answer.value}

    def row(
        self, item: str, answer: Any, *, context: SessionContext, playback: Playback | None
    ) -> dict[str, Any]:
        return self._row(context=context, playback=playback, item=item, rt_s=answer.rt_s,
                         timestamp=answer.timestamp, response=str(answer.value))  # fmt: skip


def ssq_screens(moment: str) -> list[SsqScreen]:
    """The 16 screens of one administration (``moment`` before or after), in the
    questionnaire's order."""
    return [
        SsqScreen(
            trial=Trial(
                trial_index=0,
                block="ssq",
                set_index=0,
                stimulus_set="ssq",
                stimulus=symptom.id,
                condition=moment,
                repetition=1,
            ),
            moment=moment,
            symptom=symptom.id,
        )
        for symptom in ssq.SYMPTOMS
    ]


@dataclass(frozen=True)
class ConversationAnswer:
    """How a live conversation ended: ``ended`` ``time`` (its minutes ran out) or ``talker``
    (the talker ended it), the turns the participant's page was sent, and how long it lasted
    (``rt_s``, s)."""

    ended: str
    turns: int
    rt_s: float
    timestamp: str


@screen_kind
@dataclass(frozen=True)
class ConversationScreen(ResponseScreen):
    """A live conversation (``presentation.conversation``, issue 53.4): the partner's avatar,
    driven by the talker's streamed voice under ``condition``'s method, for ``seconds`` or
    until the talker ends it. Logged as item ``conversation`` on the conversation's own trial
    (index 0, block ``conversation``, stimulus ``partner``): ``response`` how it ended,
    ``score`` the turns, ``rt_s`` how long it lasted. Online the server relays the talker to
    the participant's page; in the lab the window's ``conversation_host`` (facelab run's live
    server) draws the partner in the session's window; the turns are recorded in the
    participant's folder either way. A simulated participant answers it at once."""

    kind: ClassVar[str] = "conversation"
    condition: str = ""
    seconds: float = 0.0
    text: str = ""

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        return ((0, "conversation"),)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {
            "kind": self.kind, "trial_index": 0, "item": "conversation", "practice": False,
            "condition": self.condition, "seconds": self.seconds, "text": self.text,
        }  # fmt: skip

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> ConversationAnswer:
        ended = posted.get("ended")
        if ended not in ("time", "talker"):
            raise AnswerError(f"ended: expected 'time' or 'talker', got {ended!r}")
        turns = posted.get("turns")
        if isinstance(turns, bool) or not isinstance(turns, int) or not 0 <= turns <= 100_000:
            raise AnswerError(f"turns: expected a whole number from 0, got {turns!r}")
        return ConversationAnswer(ended, turns, rt_s, timestamp)

    def posted(self, answer: Any) -> dict[str, Any]:
        return {"ended": answer.ended, "turns": answer.turns}

    def row(
        self, item: str, answer: Any, *, context: SessionContext, playback: Playback | None
    ) -> dict[str, Any]:
        return self._row(context=context, playback=playback, item=item, rt_s=answer.rt_s,
                         timestamp=answer.timestamp, response=answer.ended,
                         score=float(answer.turns))  # fmt: skip


def conversation_screens(protocol: Protocol) -> list[Screen]:
    """The conversation of ``presentation.conversation`` and the VAS items about the partner
    after it (one screen each, or together as ``items_layout`` says); none without one."""
    conv = protocol.presentation.conversation
    if conv is None:
        return []
    lang = protocol.presentation.language
    trial = Trial(trial_index=0, block="conversation", set_index=0,
                  stimulus_set="conversation", stimulus="partner",
                  condition=conv.condition, repetition=1)  # fmt: skip
    texts = ui(lang)
    talk = ConversationScreen(trial=trial, condition=conv.condition, seconds=conv.minutes * 60.0,
                              text=localized(conv.text, lang, texts["conversation"]))  # fmt: skip
    screens: list[Screen] = [talk]
    wanted = conv.items
    items = tuple(i for i in protocol.items if wanted is None or i.id in wanted)
    if not items:
        return screens
    screens.append(TextScreen(role="partner", text=texts["partner"]))
    if protocol.presentation.items_layout == "together":
        return [*screens, VasScreen(trial=trial, items=items)]
    return [*screens, *(VasScreen(trial=trial, items=(item,)) for item in items)]


def _vas_screens(
    protocol: Protocol, trial: Trial | None, *, practice: bool, level: float | None = None
) -> list[VasScreen]:
    items = tuple(protocol.items)
    if protocol.presentation.items_layout == "together":
        return [VasScreen(trial=trial, practice=practice, items=items, level=level)]
    return [VasScreen(trial=trial, practice=practice, items=(item,), level=level) for item in items]


def trial_screens(
    protocol: Protocol,
    trial: Trial,
    *,
    practice: bool = False,
    task: AnyTask | None = None,
) -> list[Screen]:
    """The screens of one trial: its clip(s), then its response screen(s).

    ``task`` overrides the block's task (the practice trial uses the first block's)."""
    if trial.condition == PENDING:
        return [AdaptiveTrial(trial=trial, protocol=protocol)]
    screens = _task_screens(protocol, trial, practice=practice, task=task)
    if practice or not protocol.presentation.added_screens:
        return screens
    level = protocol.condition(trial.condition).level
    for spec in protocol.presentation.added_screens:
        cls = _added_kind(spec.kind)
        options = cls.Options.model_validate(dict(spec.options))  # type: ignore[attr-defined]
        screen = cls(trial=trial, practice=False, level=level, options=options)  # type: ignore[call-arg]
        if getattr(cls, "placement", "after_responses") == "after_clip":
            last_clip = max(i for i, s in enumerate(screens) if isinstance(s, ClipScreen))
            screens.insert(last_clip + 1, screen)
        else:
            screens.append(screen)
    return screens


def _added_kind(name: str) -> type[Screen]:
    """The screen kind ``name`` of a protocol's added screen: registered, or an installed
    package's (entry points ``facelab.screens``, registered here on first use)."""
    if name not in SCREEN_KINDS:
        from facelab.plugins import GROUPS, loaded

        for entry in loaded(GROUPS["screens"]):
            obj = entry.obj
            if entry.name == name and isinstance(obj, type) and issubclass(obj, ResponseScreen):
                screen_kind(obj)
    if name not in SCREEN_KINDS:
        raise ValueError(f"presentation.added_screens: unknown screen kind {name!r}")
    return SCREEN_KINDS[name]


def _task_screens(
    protocol: Protocol,
    trial: Trial,
    *,
    practice: bool,
    task: AnyTask | None,
) -> list[Screen]:
    """The clip(s) and response screen(s) of one trial (see :func:`trial_screens`)."""
    block = next((b for b in protocol.blocks if b.id == trial.block), None)
    if task is None and block is not None:
        task = protocol.block_task(block)
    level = protocol.condition(trial.condition).level
    shown = None if practice else trial
    clip = (trial.stimulus_set, trial.stimulus, trial.condition)
    if task is None:
        return [
            ClipScreen(trial=shown, clip=clip, practice=practice),
            *_vas_screens(protocol, shown, practice=practice, level=level),
        ]
    if isinstance(task, IdentifyTask):
        return [
            ClipScreen(trial=shown, clip=clip, practice=practice),
            IdentifyScreen(trial=shown, practice=practice, level=level, task=task),
        ]
    if isinstance(task, MatrixTask):
        stimulus = next(st for st in protocol.stimulus_set(trial.stimulus_set).stimuli
                        if st.id == trial.stimulus)  # fmt: skip
        return [
            ClipScreen(trial=shown, clip=clip, practice=practice),
            MatrixScreen(trial=shown, practice=practice, level=level, task=task,
                         said=" ".join(task.words_said(stimulus) or [])),
        ]  # fmt: skip
    if isinstance(task, TypedTask):
        stimulus = next(st for st in protocol.stimulus_set(trial.stimulus_set).stimuli
                        if st.id == trial.stimulus)  # fmt: skip
        keywords = task.keywords_of(stimulus)
        return [
            ClipScreen(trial=shown, clip=clip, practice=practice),
            TypedScreen(trial=shown, practice=practice, level=level, task=task,
                        said=task.said(stimulus) or "",
                        keywords=None if keywords is None else tuple(keywords)),
        ]  # fmt: skip
    standard = (trial.stimulus_set, trial.stimulus, trial.standard or task.standard)
    first, second = (clip, standard) if (trial.position or 1) == 1 else (standard, clip)
    if task.layout == "side_by_side":  # position: the comparison's side, 1 left, 2 right
        return [
            ClipPairScreen(
                trial=shown,
                clip=first,
                right=second,
                practice=practice,
                sound=1 if first == standard else 2,
            ),
            ChoiceScreen(trial=shown, practice=practice, level=level, task=task),
        ]
    return [
        ClipScreen(trial=shown, clip=first, practice=practice, interval=1),
        ClipScreen(trial=shown, clip=second, practice=practice, interval=2, gap_s=task.gap_s),
        ChoiceScreen(trial=shown, practice=practice, level=level, task=task),
    ]


def compile_timeline(
    protocol: Protocol, trials: Sequence[Trial], *, participant: str, session: int
) -> list[Screen]:
    """Every screen of a session, in order (see the module docstring)."""
    pres = protocol.presentation
    lang = pres.language
    texts = ui(lang)
    screens: list[Screen] = [
        TextScreen(role="welcome", text=texts["welcome"].format(pid=participant, ses=session))
    ]
    if "before" in pres.ssq:
        screens += ssq_screens("before")
    if pres.instructions:
        screens.append(TextScreen(role="instructions", text=localized(pres.instructions, lang)))
    if pres.practice is not None:
        first = trials[0].block if trials else protocol.blocks[0].id  # this participant's
        task = protocol.block_task(next(b for b in protocol.blocks if b.id == first))
        practice = Trial(
            trial_index=0,
            block="practice",
            set_index=1,
            stimulus_set=pres.practice.stimulus_set,
            stimulus=pres.practice.stimulus,
            condition=pres.practice.condition,
            repetition=1,
            standard=task.standard if isinstance(task, ChoiceTask) else None,
            position=1 if isinstance(task, ChoiceTask) else None,
        )
        screens.append(TextScreen(role="practice", text=texts["practice"]))
        screens += trial_screens(protocol, practice, practice=True, task=task)
    conversation = pres.conversation
    if conversation is not None and conversation.when == "before":
        screens += conversation_screens(protocol)
    blocks = {b.id: b for b in protocol.blocks}
    for i, trial in enumerate(trials):
        screens += trial_screens(protocol, trial)
        nxt = trials[i + 1] if i + 1 < len(trials) else None
        if nxt is not None and nxt.block != trial.block and blocks[trial.block].break_after:
            text = localized(pres.break_text, lang, texts["break"])
            screens.append(TextScreen(role="break", text=text))
    if conversation is not None and conversation.when == "after":
        screens += conversation_screens(protocol)
    if "after" in pres.ssq:
        screens += ssq_screens("after")
    screens.append(TextScreen(role="end", text=localized(pres.end_text, lang, texts["end"])))
    return screens


#: words of the keyboard and mouse: a text naming them needs its own VR wording
_DESK_WORDS = re.compile(
    r"スペース|キーを|キーで|キーボード|数字キー|クリック|マウス"
    r"|\b(?:space(?:bar)?|keys?|keyboard|click(?:ing|s)?|mouse)\b",
    re.IGNORECASE,
)


def _desk_words(text: Mapping[str, str]) -> list[str]:
    return sorted({m.group(0).lower() for t in text.values() for m in _DESK_WORDS.finditer(t)})


def vr_texts(protocol: Protocol) -> dict[str, str]:
    """Role -> the text a text screen shows in VR (``display: webxr``), where answers are given
    with a controller or by gaze: ``presentation.vr``'s own texts; a break without one gets
    facelab's VR wording when the 2D text names keys or clicks (facelab's own does), the
    resume notice always. Empty for other displays."""
    pres = protocol.presentation
    if pres.display != "webxr":
        return {}
    lang, vr = pres.language, pres.vr
    out = {"resume": ui(lang)["resume_vr"]}
    if vr.break_text or not pres.break_text or _desk_words(pres.break_text):
        out["break"] = localized(vr.break_text, lang, ui(lang)["break_vr"])
    if vr.instructions:
        out["instructions"] = localized(vr.instructions, lang)
    if vr.end_text:
        out["end"] = localized(vr.end_text, lang)
    return out


def vr_wording_notes(protocol: Protocol) -> list[str]:
    """Notes on a VR protocol's texts that speak of keys or mouse clicks with no VR wording
    of their own (``facelab validate`` prints them)."""
    pres = protocol.presentation
    if pres.display != "webxr":
        return []
    notes = []
    if pres.vr.instructions is not None and pres.instructions is None:
        notes.append("presentation.vr.instructions is not shown: the session shows "
                     "instructions only when presentation.instructions is given")  # fmt: skip
    for key in ("instructions", "break_text", "end_text"):
        text = getattr(pres, key)
        if not text or getattr(pres.vr, key) is not None:
            continue
        words = _desk_words(text)
        if words:
            shown = ("facelab's VR break text is shown instead" if key == "break_text"
                     else "it is shown as it is")  # fmt: skip
            notes.append(
                f"presentation.{key} speaks of the keyboard or mouse ({', '.join(words)}), but "
                f"in VR participants answer with a controller or their gaze - {shown}; give "
                f"presentation.vr.{key} for VR"
            )
    return notes


def needed_clips(screens: Sequence[Screen]) -> set[ClipKey]:
    """Every clip the screens may show: a staircase trial may show any level of its grid."""
    needed: set[ClipKey] = set()
    for s in screens:
        if isinstance(s, ClipScreen):
            needed.update(s.clips())
        elif isinstance(s, AdaptiveTrial):
            assert s.trial is not None and s.protocol is not None
            block = next(b for b in s.protocol.blocks if b.id == s.trial.block)
            for cond in s.protocol.block_conditions(block):
                needed |= {
                    c for x in s.expand(cond) if isinstance(x, ClipScreen) for c in x.clips()
                }
    return needed


def _question_due(screens: Sequence[Screen], i: int, answered: set[tuple[int, str]]) -> bool:
    """Whether the first response screen after screen ``i`` has a response still to give."""
    nxt = next((x for x in screens[i + 1 :] if isinstance(x, ResponseScreen)), None)
    return nxt is not None and any(k not in answered for k in nxt.response_keys())


def remaining(
    screens: Sequence[Screen], answered: set[tuple[int, str]], *, language: str
) -> list[Screen]:
    """The screens still to show when ``answered`` responses are already logged."""
    if not answered:
        return list(screens)
    if all((ssq.parse_item(item) or ("",))[0] == "before" for _, item in answered):
        # stopped inside the questionnaire before the study (its answers are trial 0): the
        # study has not begun, so its instructions and practice are still to come (an
        # answered conversation or trial means it has)
        out = [s for i, s in enumerate(screens)
               if not (isinstance(s, ResponseScreen) and s.response_keys()
                       and all(k in answered for k in s.response_keys()))
               and not (isinstance(s, TextScreen) and s.role == "partner"
                        and not _question_due(screens, i, answered))]  # fmt: skip
        return [out[0], TextScreen(role="resume", text=ui(language)["resume"]), *out[1:]]
    missing_trials = {
        s.trial_index
        for s in screens
        if isinstance(s, ResponseScreen) and any(k not in answered for k in s.response_keys())
    }
    out: list[Screen] = []
    for i, s in enumerate(screens):
        if isinstance(s, TextScreen):
            if s.role == "welcome":
                out += [s, TextScreen(role="resume", text=ui(language)["resume"])]
            elif s.role in ("break", "end"):
                out.append(s)
            elif s.role == "partner" and _question_due(screens, i, answered):
                out.append(s)  # kept while a question about the partner is to come
            continue  # instructions and the practice announcement are not repeated
        if getattr(s, "practice", False):
            continue
        if s.trial_index not in missing_trials:
            continue
        if isinstance(s, ResponseScreen) and all(k in answered for k in s.response_keys()):
            continue
        out.append(s)
    # a break is useful only between screens that are still to come
    pruned: list[Screen] = []
    for i, s in enumerate(out):
        if isinstance(s, TextScreen) and s.role == "break":
            before = any(x.trial_index is not None for x in pruned)
            after = any(x.trial_index is not None for x in out[i + 1 :])
            if not (before and after):
                continue
        pruned.append(s)
    return pruned
