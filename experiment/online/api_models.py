"""What the browser may send: every request body as a strict model (every field checked,
unknown fields refused)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

__all__ = ["AnswerIn", "EventIn", "PlaybackIn"]

Key = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{8,64}$")]
ItemId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_.-]{1,64}$")]
Iso = Annotated[str, StringConstraints(max_length=40)]


class _Strict(BaseModel):
    # NaN and infinity are refused everywhere: PostgreSQL's JSON cannot hold them (a 500),
    # and SQLite stored them as numbers no analysis can use
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class AnswerIn(_Strict):
    """One answer from the browser (every field checked; unknown fields refused)."""

    client_key: Key
    trial_index: int = Field(ge=1, le=100_000)
    item: ItemId
    rt_s: float = Field(ge=0, le=86_400)
    rating: float | None = Field(None, ge=-1e6, le=1e6)
    choice: int | None = Field(None, ge=1, le=2)
    label: ItemId | None = None
    # the answer of a screen kind added to facelab (its Screen.answer reads and checks it)
    value: (
        Annotated[float, Field(ge=-1e6, le=1e6)]
        | Annotated[str, StringConstraints(max_length=64)]
        | None
    ) = None
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
    # to the avatar's face; viewer_poses: [t s, x, y, z m, yaw, pitch, roll deg] per frame
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


class EventIn(_Strict):
    kind: Literal["browser", "play_refused", "fullscreen_exit", "resumed", "error", "display"]
    detail: dict[str, Any] = Field(default_factory=dict)
