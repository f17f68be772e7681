"""``facelab impression render``: one clip per impression level, ``clips.csv``, a contact sheet
and a channel plot (see :mod:`facelab.stimuli.impression.model` for the model and the easing).

ARKit-space models play on the default head or any avatar with the ARKit targets the
direction uses; vertex-space models play on their own mean neutral mesh (the database's
topology). Clips are silent (a neutral lead-in, eased onset, hold, eased offset); the file
name carries the level, ``<expression>__q<level>.mp4``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.formats import write_manifest
from facelab.grid import SERIAL, Cluster, GridTask, Progress
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.impression.model import ImpressionModel, envelope
from facelab.stimuli.render.renderer import Renderer, RenderSettings
from facelab.stimuli.render.scene import face_closeup
from facelab.stimuli.render.task import (
    ClipFrames,
    RenderedClip,
    audio_sha256,
    finish_grid,
    render_clip,
    render_grid,
    shared_avatar,
    write_clip,
)
from facelab.stimuli.speech.audio import Speech

__all__ = ["IMPRESSION_CLIP_COLUMNS", "Timing", "clip_name", "render_levels"]

IMPRESSION_CLIP_COLUMNS = (
    "clip_id", "expression", "q_intended", "q_realised", "clipped_channels", "headroom_q",
    "decision_value",
    "path", "duration_s", "fps", "width", "height", "sha256", "avatar", "space", "label",
    "model_sha256",
)  # fmt: skip


@dataclass(frozen=True)
class Timing:
    """Seconds of neutral lead-in, onset, hold and offset; easing kind and sigmoid k."""

    lead_s: float = 0.3
    onset_s: float = 0.6
    hold_s: float = 1.2
    offset_s: float = 0.6
    ease: str = "sigmoid"
    k: float = 5.0

    def envelope(self, fps: int) -> np.ndarray:
        return envelope(
            fps=fps, onset_s=self.onset_s, hold_s=self.hold_s, offset_s=self.offset_s,
            lead_s=self.lead_s, kind=self.ease, k=self.k,
        )  # fmt: skip


def clip_name(expression: str, q: float) -> str:
    """``open_smile__q0.5`` (levels as written: 0, 0.5, 1, -0.25 …)."""
    return f"{expression}__q{q:g}"


def _vertex_avatar(model: ImpressionModel) -> Avatar:
    if model.faces is None:
        raise StageError("this vertex-space model has no faces to render")
    neutral = model.neutral_mean.reshape(-1, 3)
    return Avatar(
        neutral, model.faces, {}, {}, None, "impression mean face", source={"kind": "mesh"}
    )


def _frames_for(
    model: ImpressionModel, avatar: Avatar, expression: str, q: float, env: np.ndarray
) -> tuple[Avatar, np.ndarray, dict]:
    """The avatar to draw and (T, K) weights in its target order, plus the clip facts."""
    faces, info = model.frames(expression, q, env)
    if model.space == "arkit":
        lacking = [
            n
            for n, col in zip(ARKIT_NAMES, faces.T, strict=True)
            if np.any(col > 1e-6) and n not in avatar.targets
        ]
        if lacking:
            raise StageError(
                f"avatar {avatar.name!r} lacks ARKit targets the impression uses: "
                f"{', '.join(lacking[:8])}"
            )
        index = {n: i for i, n in enumerate(avatar.target_names)}
        weights = np.zeros((len(env), len(index)), np.float32)
        for j, name in enumerate(ARKIT_NAMES):
            if name in index:
                weights[:, index[name]] = faces[:, j]
        return avatar, weights, info
    # vertices: one target, the clip's full displacement, weighted by the envelope
    peak = int(np.argmax(env))
    shape = ((faces[peak] - model.neutral_mean) / max(env[peak], 1e-9)).reshape(-1, 3)
    drawn = avatar.replace(targets={"impression": shape.astype(np.float32)})
    return drawn, env[:, None].astype(np.float32), info


def render_levels(
    model: ImpressionModel,
    *,
    expression: str,
    levels: list[float],
    out: Path,
    avatar: Avatar | None = None,
    settings: RenderSettings | None = None,
    fps: int = 30,
    timing: Timing = Timing(),
    cluster: Cluster = SERIAL,
    progress: Progress | None = None,
    log=print,
) -> list[dict]:
    """Render one clip per level into ``out``; write ``clips.csv`` (keeping the rows of other
    clips rendered earlier into ``out``, e.g. another expression), ``contact_<expression>.png``
    (the peak face at each level and the direction's largest weights) and
    ``channels_<expression>.png`` (a few channels frame by frame through the highest level's
    clip); return the rows."""
    from facelab.hashing import sha256_text
    from facelab.stimuli.avatar import default_head

    if not levels:
        raise StageError("give at least one level")
    twice = sorted({clip_name(expression, q) for q in levels if levels.count(q) > 1})
    if twice:
        raise StageError(f"levels given twice: {', '.join(twice)} (each level is one clip)")
    model.model(expression)
    out.mkdir(parents=True, exist_ok=True)
    settings = settings or RenderSettings(width=1280, height=720)
    if model.space == "vertices":
        avatar = _vertex_avatar(model)
    avatar = avatar or default_head()
    env = timing.envelope(fps)
    n = len(env)
    rate = 48_000
    silence = Speech(np.zeros(round(n / fps * rate), np.float32), rate, source="silence")
    audio_hash = audio_sha256(silence)
    framing = shared_avatar(avatar)
    # of the model's content (canonical JSON), so a re-saved file keeps its hash
    model_hash = sha256_text(json.dumps(model.to_json(), sort_keys=True))
    rows: dict[str, dict] = {}
    peaks: dict[str, tuple[Avatar, np.ndarray]] = {}
    tasks = []
    for q in levels:  # every level's frames are made here (cheap); workers draw and encode
        drawn, weights, info = _frames_for(model, avatar, expression, q, env)
        name = clip_name(expression, q)
        drawn_ref = framing if drawn is avatar else shared_avatar(drawn)
        frames = ClipFrames(
            clip_id=name, weights=weights, poses=None, audio=silence, audio_sha256=audio_hash,
            fps=fps, settings=settings, framing_sha256=framing.sha256,
            drawn_sha256=drawn_ref.sha256,
        )  # fmt: skip
        tasks.append(GridTask(name, render_clip, (frames, framing, drawn_ref)))
        peaks[name] = (drawn, weights[int(np.argmax(env))])
        rows[name] = {
            "clip_id": name,
            **info,
            "path": f"{name}.mp4",
            "duration_s": None,
            "fps": fps,
            "width": settings.width,
            "height": settings.height,
            "sha256": None,
            "avatar": avatar.name,
            "space": model.space,
            "label": model.label,
            "model_sha256": model_hash,
        }

    def finished(name: str, rendered: RenderedClip) -> None:
        clip = write_clip(rendered, out=out / rows[name]["path"])
        rows[name].update(duration_s=round(clip.duration_s, 6), sha256=clip.sha256)

    report = render_grid(tasks, cluster=cluster, on_result=finished, progress=progress)
    finish_grid(report, rows=list(rows.values()), out=out, log=log)
    rows = list(rows.values())
    notes = write_manifest(
        out, rows, columns=IMPRESSION_CLIP_COLUMNS, merge=True, provenance="model_sha256"
    )
    for note in notes:
        log(note)
    # the sheet shows the face close up: a second (square, nearer) camera after the first
    # context is closed (pyrender's EGL platform holds one at a time)
    tiles = []
    with Renderer(avatar, face_closeup(avatar, size_px=420)) as r:
        for drawn, w in peaks.values():
            r.avatar = drawn
            tiles.append(r.frame(w))
    _contact_sheet(model, expression, rows, tiles, out / f"contact_{expression}.png")
    _channel_plot(
        model, expression, max(levels), env, fps, timing, out / f"channels_{expression}.png"
    )
    return rows


#: how much the contact sheet amplifies the difference images (so a step of a few grey levels
#: shows; the sheet states the factor)
DIFF_GAIN = 4


def _contact_sheet(
    model: ImpressionModel, expression: str, rows: list[dict], peaks: list[np.ndarray], path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = model.model(expression)
    n = len(peaks)
    # top row: the peak face at each level; bottom row: where and how much it differs from
    # the lowest level's face (absolute RGB difference, amplified so that a step shows)
    fig = plt.figure(figsize=(3.0 * n + 6.0, 6.6))
    outer = fig.add_gridspec(1, 2, width_ratios=[3.0 * n, 4.0], wspace=0.45)
    grid = outer[0].subgridspec(2, n, hspace=0.12, wspace=0.04)
    squares = []
    for img in peaks:
        h, w = img.shape[:2]
        side = min(h, w)
        squares.append(img[(h - side) // 2 : (h + side) // 2, (w - side) // 2 : (w + side) // 2])
    base = squares[0].astype(float)
    for i, (row, img) in enumerate(zip(rows, squares, strict=True)):
        ax = fig.add_subplot(grid[0, i])
        ax.imshow(img)
        ax.set_title(f"q = {row['q_intended']:g} (realised {row['q_realised']:.2f})", fontsize=9)
        ax.axis("off")
        ax = fig.add_subplot(grid[1, i])
        diff = np.abs(img.astype(float) - base).mean(axis=2)
        ax.imshow(np.clip(diff * DIFF_GAIN, 0, 255), cmap="magma", vmin=0, vmax=255)
        ax.set_title(
            f"|face - q = {rows[0]['q_intended']:g}| x{DIFF_GAIN}: mean {diff.mean():.2f}/255",
            fontsize=8,
        )
        ax.axis("off")
    ax = fig.add_subplot(outer[1])
    if model.space == "arkit":
        order = np.argsort(-np.abs(m.direction))[:10]
        ax.barh([ARKIT_NAMES[j] for j in order][::-1], m.direction[order][::-1], color="#4c72b0")
        ax.set_xlabel("weight in the unit direction")
        ax.tick_params(axis="y", labelsize=8)
    else:
        disp = np.linalg.norm(m.direction.reshape(-1, 3), axis=1)
        ax.hist(disp, bins=30, color="#4c72b0")
        ax.set_xlabel("per-vertex length of the unit direction")
    ax.set_title(f"{model.label} direction ({model.method})", fontsize=9)
    fig.suptitle(
        f"{expression}: impression '{model.label}' at each level (δ = {m.delta:.3g}; "
        f"LOPO {', '.join(f'{k} {v}' for k, v in m.cv.items() if k in ('accuracy', 'r2'))})",
        fontsize=10,
    )
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _channel_plot(
    model: ImpressionModel, expression: str, q: float, env: np.ndarray, fps: int, timing: Timing,
    path: Path,
) -> None:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    faces, _ = model.frames(expression, q, env)
    t = np.arange(len(env)) / fps
    fig, ax = plt.subplots(figsize=(8, 4))
    if model.space == "arkit":
        change = np.abs(faces[int(np.argmax(env))] - faces[0])
        for j in np.argsort(-change)[:5]:
            ax.plot(t, faces[:, j], marker=".", ms=3, label=ARKIT_NAMES[j])
        ax.set_ylabel("ARKit coefficient")
    else:
        ax.plot(t, env, marker=".", ms=3, label="expression weight")
        ax.set_ylabel("weight")
    ax.plot(t, env, color="grey", ls=":", label=f"e(t): {timing.ease}, k = {timing.k:g}")
    ax.set_xlabel("time (s)")
    ax.set_title(f"{clip_name(expression, q)}: channels frame by frame ({fps} fps)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
