"""One clip as a self-contained task: its frame weights, poses and audio in, mp4 bytes out.

The render commands drive every method in the calling process (a method never runs twice)
and hand each clip to :func:`render_clip` through :func:`facelab.grid.run_grid` - in this
process's grid child (:func:`render_cluster`) or on a Dask worker. What travels is content:
the (n_frames, K) weights, the head poses, the padded audio and the avatar, each checked
against its SHA-256 before use. The task encodes into its own scratch folder and returns the
file's bytes; only the calling process writes into the clip folder (:func:`write_clip`, a
temporary name renamed into place), so a worker lost mid-clip leaves nothing behind and a
task run twice writes the same bytes.

Each worker process (and the grid child) keeps one renderer open between its tasks (one EGL
context per process).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facelab.durable import replace_file
from facelab.errors import StageError
from facelab.formats import POSE_CHANNELS, Track, decode_track, encode_track
from facelab.grid import (
    Cluster,
    GridReport,
    GridTask,
    Progress,
    Shared,
    check_shared,
    run_grid,
)
from facelab.hashing import sha256_file
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.rig import HeadPose
from facelab.stimuli.render.clip import ClipInfo, encode
from facelab.stimuli.render.renderer import Renderer, RenderSettings
from facelab.stimuli.speech.audio import Speech

__all__ = [
    "ClipFrames",
    "RenderedClip",
    "audio_sha256",
    "clip_track",
    "close_renderer",
    "finish_grid",
    "render_clip",
    "render_grid",
    "shared_avatar",
    "track_frames",
    "write_clip",
]


@dataclass(frozen=True)
class ClipFrames:
    """Everything a worker needs for one clip besides the avatar(s).

    ``weights`` (n_frames, K) float32 in the drawn avatar's ``target_names`` order;
    ``poses`` one head pose per frame or None; ``audio`` the clip's whole (padded) sound.
    The renderer is framed on the ``framing`` avatar and draws the ``drawn`` one (the same
    avatar except where an impression model swaps the target stack)."""

    clip_id: str
    weights: np.ndarray
    poses: tuple[HeadPose, ...] | None
    audio: Speech
    audio_sha256: str
    fps: int
    settings: RenderSettings
    framing_sha256: str
    drawn_sha256: str
    blank: bool = False  # no face: every frame the background (an audio_only condition)

    @property
    def n_frames(self) -> int:
        return len(self.weights)


@dataclass(frozen=True)
class RenderedClip:
    """A rendered clip's bytes, their SHA-256, and the seconds spent in the task."""

    clip_id: str
    data: bytes
    sha256: str
    frames: int
    fps: int
    width: int
    height: int
    duration_s: float
    seconds: float
    pid: int


def clip_track(
    *,
    clip_id: str,
    avatar: Avatar,
    avatar_sha256: str,
    weights: np.ndarray,
    poses: list[HeadPose | None] | None,
    fps: int,
    sample_rate: int,
    speech_start_s: float,
) -> tuple[bytes, np.ndarray, tuple[HeadPose, ...] | None]:
    """A clip's animation track (:func:`facelab.formats.encode_track`) and the weights
    (n_frames, K) and poses read back from it - what the renderer then draws, so the offline
    clip and a browser playing the track show the same values. The track keeps the targets the
    clip moves; ``poses`` None or all at rest: no pose channels."""
    weights = np.asarray(weights, np.float32)
    names = list(avatar.target_names)
    active = [j for j in range(len(names)) if np.any(weights[:, j] != 0)]
    pose_rows = None
    if poses is not None and any(p is not None and not p.is_rest() for p in poses):
        rest = HeadPose()
        pose_rows = np.array(
            [
                [q.yaw, q.pitch, q.roll, q.eye_yaw, q.eye_pitch, q.neck_share]
                for q in (p if p is not None else rest for p in poses)
            ],
            np.float32,
        )
    data = encode_track(
        clip_id=clip_id, fps=fps, blendshapes=[names[j] for j in active],
        weights=weights[:, active], poses=pose_rows, sample_rate=sample_rate,
        speech_start_s=speech_start_s, avatar_sha256=avatar_sha256,
    )  # fmt: skip
    return (data, *track_frames(decode_track(data), avatar))


def track_frames(track: Track, avatar: Avatar) -> tuple[np.ndarray, tuple[HeadPose, ...] | None]:
    """The (n_frames, K) weights in ``avatar.target_names`` order and the head poses (None
    without pose channels) of a track."""
    index = {n: i for i, n in enumerate(avatar.target_names)}
    weights = np.zeros((track.header["n_frames"], len(index)), np.float32)
    poses = None
    for j, ch in enumerate(track.header["channels"]):
        if ch["kind"] == "blendshape":
            if ch["name"] not in index:
                raise StageError(f"the track drives {ch['name']!r}, which the avatar lacks")
            weights[:, index[ch["name"]]] = track.values[:, j]
    if "head_yaw" in track.names:
        cols = track.values[:, [track.names.index(c) for c in POSE_CHANNELS]].astype(float)
        poses = tuple(HeadPose(*map(float, row)) for row in cols)
    return weights, poses


def audio_sha256(audio: Speech) -> str:
    h = hashlib.sha256(np.ascontiguousarray(audio.samples, np.float32).tobytes())
    h.update(str(audio.sample_rate).encode())
    return h.hexdigest()


def shared_avatar(avatar: Avatar) -> Shared:
    return Shared(avatar.content_hash(), avatar)


_open: dict[str, object] = {}  # this process's one open renderer and what it was opened for
_checked: dict[int, str] = {}  # id of an avatar object already hash-checked -> its hash


def _checked_avatar(avatar: Avatar, sha256: str, what: str) -> Avatar:
    if _checked.get(id(avatar)) != sha256:
        check_shared(avatar, sha256=sha256, content_hash=Avatar.content_hash, what=what)
        _checked[id(avatar)] = sha256
    return avatar


def _renderer(framing: Avatar, framing_sha: str, settings: RenderSettings) -> Renderer:
    key = f"{framing_sha}|{settings!r}"
    if _open.get("key") != key:
        close_renderer()
        _open["renderer"] = Renderer(framing, settings).__enter__()
        _open["key"] = key
    return _open["renderer"]  # type: ignore[return-value]


def close_renderer() -> None:
    """Close this process's open renderer (before another GL context is opened here)."""
    renderer = _open.pop("renderer", None)
    _open.pop("key", None)
    if renderer is not None:
        renderer.__exit__(None, None, None)


def render_clip(job: ClipFrames, framing: Avatar, drawn: Avatar) -> RenderedClip:
    """Render and encode one clip; its bytes (runs in a worker or in this process)."""
    started = time.perf_counter()
    _checked_avatar(framing, job.framing_sha256, f"the avatar of {job.clip_id}")
    _checked_avatar(drawn, job.drawn_sha256, f"the drawn avatar of {job.clip_id}")
    check_shared(
        job.audio, sha256=job.audio_sha256, content_hash=audio_sha256,
        what=f"the audio of {job.clip_id}",
    )  # fmt: skip
    if job.weights.shape != (job.n_frames, len(drawn.target_names)):
        raise StageError(
            f"{job.clip_id}: weights of shape {job.weights.shape}, expected "
            f"({job.n_frames}, {len(drawn.target_names)})"
        )
    renderer = _renderer(framing, job.framing_sha256, job.settings)
    renderer.avatar = drawn  # same vertices and faces as the framing avatar
    try:
        if job.blank:  # the background as the renderer draws it (its corner pixel)
            first = next(iter(renderer.frames(job.weights[:1])))
            plain = np.empty_like(first)
            plain[...] = first[0, 0]
            frames = (plain for _ in range(job.n_frames))
        elif job.poses is None:
            frames = renderer.frames(job.weights)
        else:
            frames = renderer.frames(job.weights, job.poses)
        with tempfile.TemporaryDirectory(prefix="facelab-task-") as scratch:
            info = encode(
                frames, audio=job.audio, out=Path(scratch) / f"{job.clip_id}.mp4", fps=job.fps,
                width=job.settings.width, height=job.settings.height, n_frames=job.n_frames,
            )  # fmt: skip
            data = info.path.read_bytes()
    finally:
        renderer.avatar = framing
    return RenderedClip(
        job.clip_id, data, info.sha256, job.n_frames, job.fps, job.settings.width,
        job.settings.height, info.duration_s, time.perf_counter() - started, os.getpid(),
    )  # fmt: skip


def render_cluster(cluster: Cluster) -> Cluster:
    """Where :func:`render_grid` renders on ``cluster``: a serial grid in this process's grid
    child (:mod:`facelab.grid`), so that an OpenGL driver that crashes mid-clip (llvmpipe
    aborted twice in ~15 full test runs here) costs that clip a re-run, not the command. (The
    child is POSIX-only - it is handed a socket - so elsewhere a serial grid stays in this
    process.)"""
    if cluster.serial and os.name == "posix":
        return dataclasses.replace(cluster, child_process=True)
    return cluster


def render_grid(
    tasks: Iterable[GridTask],
    *,
    cluster: Cluster,
    on_result: Callable[[str, Any], None],
    progress: Progress | None = None,
    isolate: bool = True,
) -> GridReport:
    """:func:`facelab.grid.run_grid` for render tasks on :func:`render_cluster` (``isolate``
    False: a serial grid renders in this process, as benchmarks of this process's CPU want):
    each clip's bytes go to ``on_result`` and are not kept in the report, and this process's
    renderer (opened by tasks run here) is closed afterwards, whatever happened, so the caller
    may open another GL context."""
    try:
        return run_grid(
            tasks, cluster=render_cluster(cluster) if isolate else cluster,
            on_result=on_result, progress=progress, keep_results=False,
        )  # fmt: skip
    finally:
        close_renderer()


def finish_grid(report: GridReport, *, rows: list[dict], out: Path, log) -> None:
    """After a render grid: name the clips that failed (one StageError, after the others were
    written) and those a lost worker made the scheduler re-run; check that every row's file
    exists and has the row's hash."""
    if not report.where.startswith("serially") or report.retried or report.failed:
        log(f"  grid: {report.summary()}")
    if report.failed:
        lines = [f"  {key}: {why}" for key, why in sorted(report.failed.items())]
        raise StageError(
            f"{len(report.failed)} of {len(report.failed) + len(report.results)} clips failed "
            f"(the other clips are written and will be reused):\n" + "\n".join(lines)
        )

    def matches(name: str, digest: str | None) -> bool:
        return digest is not None and (out / name).is_file() and sha256_file(out / name) == digest

    wrong = [
        r["clip_id"] for r in rows
        if not matches(r["path"], r["sha256"])
        or ("track_file" in r and not matches(r["track_file"], r["track_sha256"]))
    ]  # fmt: skip
    if wrong:
        raise StageError(f"clips missing or not matching their hash: {', '.join(wrong)}")


def write_clip(rendered: RenderedClip, *, out: Path) -> ClipInfo:
    """Write a rendered clip to ``out`` under a temporary name and rename it into place;
    the written file's SHA-256 is checked against the task's."""
    if hashlib.sha256(rendered.data).hexdigest() != rendered.sha256:
        raise StageError(f"{rendered.clip_id}: the clip's bytes do not match their hash")
    out.parent.mkdir(parents=True, exist_ok=True)
    replace_file(out, rendered.data)
    if sha256_file(out) != rendered.sha256:
        raise StageError(f"{out}: written clip does not match its hash")
    r = rendered
    return ClipInfo(out, r.duration_s, r.fps, r.width, r.height, r.frames, r.sha256)
