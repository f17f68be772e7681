"""What the browser may send: every request body as a strict model (every field checked,
unknown fields refused)."""

from __future__ import annotations

import re
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

__all__ = ["AnswerIn", "EventIn", "PlaybackIn", "ScreenPosesIn"]

Key = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{8,64}$")]
ItemId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_.-]{1,64}$")]
Iso = Annotated[str, StringConstraints(max_length=40)]


#: what no text from a browser may hold: lone UTF-16 surrogates (valid JSON escapes, but no
#: UTF-8 file can hold them - one stopped every later export) and control characters (a tab
#: or newline would break a TSV row). Free text (an event's detail) may hold tab and newline.
_BAD_TEXT = re.compile(r"[\ud800-\udfff\x00-\x1f\x7f-\x9f\u2028\u2029]")
_BAD_FREE_TEXT = re.compile(
    r"[\ud800-\udfff\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\u2028\u2029]"
)  # (U+2028/9 too: line separators to Python's splitlines)
#: bounds of free JSON (an event's detail): nesting, keys, strings and items per container
MAX_DEPTH, MAX_KEY, MAX_TEXT, MAX_ITEMS = 4, 64, 2000, 200


def text_problem(value: Any, *, where: str = "", free: bool = False, depth: int = 0) -> str | None:
    """The first string in a JSON value (keys too) that holds what no text from a browser
    may hold, or free JSON over its bounds: ``"<path>: <what>"``; None when all is well."""
    pattern = _BAD_FREE_TEXT if free else _BAD_TEXT
    if isinstance(value, str):
        bad = pattern.search(value)
        if bad:
            return (f"{where or 'body'}: text with a control character or a lone surrogate "
                    f"(U+{ord(bad.group()):04X}); expected plain text")  # fmt: skip
        if free and len(value) > MAX_TEXT:
            return f"{where}: text over {MAX_TEXT} characters"
        return None
    if isinstance(value, dict | list):
        if free and depth >= MAX_DEPTH:
            return f"{where}: nested deeper than {MAX_DEPTH} levels"
        if free and len(value) > MAX_ITEMS:
            return f"{where}: more than {MAX_ITEMS} entries"
        items = value.items() if isinstance(value, dict) else enumerate(value)
        for key, inner in items:
            at = f"{where}.{key}" if where else str(key)
            if isinstance(key, str):
                if free and len(key) > MAX_KEY:
                    return f"{at[:80]}: a key over {MAX_KEY} characters"
                problem = text_problem(key, where=f"{where or 'body'} (a key)", free=free)
                if problem:
                    return problem
            problem = text_problem(inner, where=at, free=free, depth=depth + 1)
            if problem:
                return problem
    return None


class _Strict(BaseModel):
    # NaN and infinity are refused everywhere: PostgreSQL's JSON cannot hold them (a 500),
    # and SQLite stored them as numbers no analysis can use
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)
    #: fields holding free JSON (bounded, tab and newline allowed in their text)
    FREE_JSON: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="before")
    @classmethod
    def _plain_text(cls, data: Any) -> Any:
        """Every string of the body checked at the door (see :func:`text_problem`)."""
        if isinstance(data, dict):
            for key, value in data.items():
                problem = text_problem(value, where=str(key), free=key in cls.FREE_JSON)
                if problem:
                    raise ValueError(problem)
        return data


class AnswerIn(_Strict):
    """One answer from the browser (every field checked; unknown fields refused)."""

    client_key: Key
    # 0: the sickness questionnaire (outside the design; the server checks the pair
    # (trial_index, item) is one of the participant's screens either way)
    trial_index: int = Field(ge=0, le=100_000)
    item: ItemId
    rt_s: float = Field(ge=0, le=86_400)
    rating: float | None = Field(None, ge=-1e6, le=1e6)
    choice: int | None = Field(None, ge=1, le=2)
    label: ItemId | None = None
    # a typed answer (as typed; the screen normalises its whitespace and checks its length)
    text: Annotated[str, StringConstraints(max_length=400)] | None = None
    # a word-matrix answer: the word picked in each column (the screen checks them)
    words: (
        list[Annotated[str, StringConstraints(min_length=1, max_length=64)]] | None
    ) = Field(None, min_length=1, max_length=8)
    # the answer of a screen kind added to facelab (its Screen.answer reads and checks it)
    value: (
        Annotated[float, Field(ge=-1e6, le=1e6)]
        | Annotated[str, StringConstraints(max_length=64)]
        | None
    ) = None
    # a live conversation's end: how it ended and the turns the page was sent
    ended: Literal["time", "talker"] | None = None
    turns: int | None = Field(None, ge=0, le=100_000)
    timestamp: Iso
    clip_onset: float | None = Field(None, ge=0, le=1e7)
    clip_frames_dropped: int | None = Field(None, ge=0, le=1_000_000)


class PlaybackIn(_Strict):
    """How one clip was shown, as ``requestVideoFrameCallback`` saw it."""

    client_key: Key
    trial_index: int | None = Field(None, ge=1, le=100_000)
    clip: Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{64}\.mp4$")]
    replay: bool
    onset: float | None = Field(None, ge=0, le=1e7)
    frames_expected: int = Field(ge=0, le=1_000_000)
    dropped: int = Field(ge=0, le=1_000_000)
    flip_times: list[float] = Field(max_length=100_000)
    frames_shown: list[int] = Field(max_length=100_000)
    presented_frames: int = Field(ge=0, le=1_000_000)
    media_time_end: float | None = Field(None, ge=0, le=1e6)
    play_refused: str | None = Field(None, max_length=200)
    # display live3d / webxr (live.js): what ran, the audio clock at each frame (s from the
    # clip's start), frame intervals over 1.5x the median, the shown frame's centre time minus
    # the heard audio time (median, ms), and in VR the viewer's head movement and distance
    # to the avatar's face; viewer_poses: [t s, x, y, z m, yaw, pitch, roll deg] per frame;
    # controller_poses below
    display: Literal["video", "live3d", "webxr"] | None = None
    audio_times: list[float] | None = Field(None, max_length=100_000)
    frames_late: int | None = Field(None, ge=0, le=1_000_000)
    av_offset_ms: float | None = Field(None, ge=-1e6, le=1e6)
    head_yaw_range_deg: float | None = Field(None, ge=0, le=360)
    head_pitch_range_deg: float | None = Field(None, ge=0, le=360)
    avatar_distance_m: float | None = Field(None, ge=0, le=1000)
    viewer_poses: list[Annotated[list[float], Field(min_length=7, max_length=7)]] | None = Field(
        None, max_length=100_000
    )
    # VR: each tracked controller per frame, [t s, hand (0 left, 1 right, 2 neither), x, y, z m,
    # yaw, pitch, roll deg] (its grip, else its pointer; the head's reference space)
    controller_poses: (
        list[Annotated[list[float], Field(min_length=8, max_length=8)]] | None
    ) = Field(None, max_length=200_000)
    # VR: whether the voice came from the avatar's mouth (an HRTF panner) and where that was
    # (x, y, z m, the reference space's axes)
    spatial_audio: bool | None = None
    # VR: times the clip was stopped by the headset taken off (or the session ended) and
    # played again from the start once seen (the record is of the whole playing)
    interruptions: int | None = Field(None, ge=0, le=1000)
    audio_source_m: (
        Annotated[list[Annotated[float, Field(ge=-1e4, le=1e4)]], Field(min_length=3, max_length=3)]
        | None
    ) = None


class ScreenPosesIn(_Strict):
    """The head's and the controllers' poses while one VR screen waited for an answer (a VAS
    item, a choice, the questionnaire, a text): the screen's trial (None outside the trials),
    kind and item, when it was shown (page seconds), and per drawn frame the head
    ``[t s, x, y, z m, yaw, pitch, roll deg]`` and each tracked controller
    ``[t, hand (0 left, 1 right, 2 neither), x, y, z, yaw, pitch, roll]``."""

    client_key: Key
    trial_index: int | None = Field(None, ge=0, le=100_000)
    screen: Annotated[str, StringConstraints(pattern=r"^[a-z0-9_]{1,32}$")]
    item: ItemId | None = None
    role: Annotated[str, StringConstraints(pattern=r"^[a-z_]{1,32}$")] | None = None
    shown: float = Field(ge=0, le=1e7)
    viewer_poses: list[Annotated[list[float], Field(min_length=7, max_length=7)]] = Field(
        max_length=100_000
    )
    controller_poses: list[Annotated[list[float], Field(min_length=8, max_length=8)]] = Field(
        max_length=200_000
    )


class EventIn(_Strict):
    kind: Literal[
        "browser", "play_refused", "fullscreen_exit", "resumed", "error", "display", "recentre",
        "headset", "withdrawn", "withdraw_cancelled",
    ]
    detail: dict[str, Any] = Field(default_factory=dict)

    FREE_JSON: ClassVar[frozenset[str]] = frozenset({"detail"})
