"""``facelab behaviour render``: long demonstration clips of the behaviour layer, a timeline
figure per plan, and a contact sheet of the library's units.

One TTS utterance is spoken with the vowel-driven method (Z standard) after a short lead-in
and followed by silence up to ``duration_s`` (so the clip shows behaviour while speaking and
while listening); for each emotion and behaviour mode the plan is made with the same seed
(yoked) and rendered to ``<emotion>__<mode>.mp4`` with its event log
``<emotion>__<mode>.behaviour.json`` and timeline ``<emotion>__<mode>.timeline.png``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from facelab.durable import replace_file
from facelab.emotions import BEHAVIOUR_MODES
from facelab.errors import BehaviourError
from facelab.formats import write_manifest
from facelab.grid import SERIAL, Cluster, GridTask, Progress
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.behaviour.clip import ClipBehaviour, behaviour_for_clip
from facelab.stimuli.behaviour.library import ROTATIONS, Library, Unit, default_library
from facelab.stimuli.behaviour.plan import SpeechCues, blend_pose, complete_emotion
from facelab.stimuli.behaviour.realise import (
    BehaviourFrames,
    apply_to_weights,
    avatar_traits,
    curve_values,
)
from facelab.stimuli.methods import DriveInput, drive
from facelab.stimuli.render.clip import frame_weights
from facelab.stimuli.render.renderer import Renderer, RenderSettings
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
from facelab.stimuli.speech.analyser import analyze
from facelab.stimuli.speech.audio import Speech
from facelab.stimuli.speech.tts import synthesize

__all__ = ["render_behaviour_clips", "unit_sheet"]

BEHAVIOUR_CLIP_COLUMNS = (
    "clip_id", "emotion", "mode", "path", "duration_s", "fps", "width", "height", "sha256",
    "n_posture", "n_mannerism", "n_gesture", "n_blink", "blinks_per_min",
)  # fmt: skip


def _write_json(path: Path, data: dict) -> None:
    replace_file(path, json.dumps(data, indent=1, ensure_ascii=False) + "\n")


def render_behaviour_clips(
    *,
    text: str,
    emotions: list[dict[str, float]],
    modes: list[str],
    duration_s: float,
    seed: int,
    out: Path,
    avatar: Avatar,
    settings: RenderSettings,
    fps: int = 30,
    lead_s: float = 0.5,
    library: str = "default",
    base_dir: Path = Path("."),
    cluster: Cluster = SERIAL,
    progress: Progress | None = None,
    log=print,
) -> list[dict]:
    """Render every (emotion, mode) clip; returns their rows of ``out/clips.csv`` (which keeps
    the rows of other clips rendered earlier into ``out``)."""
    import matplotlib.pyplot as plt

    from facelab.stimuli.render.plots import plan_timeline_figure

    for m in modes:
        if m not in BEHAVIOUR_MODES:
            raise BehaviourError(f"mode {m!r}: use {', '.join(BEHAVIOUR_MODES)}")
    speech = synthesize(text, sample_rate=48_000)
    if speech.duration_s + lead_s > duration_s:
        raise BehaviourError(
            f"the text takes {speech.duration_s:.1f} s: --duration-s {duration_s:g} is too short"
        )
    rate = speech.sample_rate
    n_frames = round(duration_s * fps)
    tail = round(n_frames / fps * rate) - round(lead_s * rate) - len(speech.samples)
    audio = Speech(
        np.concatenate(
            [np.zeros(round(lead_s * rate), np.float32), speech.samples, np.zeros(tail, np.float32)]
        ),
        rate,
    )
    track = analyze(speech.samples, sample_rate=rate).compensated()
    bs = drive("vowel_blend", DriveInput(track=track, phones=speech.phones), {"z": "standard"})
    speech_weights = frame_weights(bs, avatar, fps=fps, n_frames=n_frames, pad_s=lead_s)
    cues = SpeechCues.from_speech(speech, offset_s=lead_s)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    setting_for = {
        m: (library if (library != "default" and m == "composite") else m) for m in modes
    }
    framing = shared_avatar(avatar)
    audio_hash = audio_sha256(audio)
    rows: dict[str, dict] = {}
    plans: dict[str, ClipBehaviour | None] = {}

    def tasks() -> Iterator[GridTask]:
        for emo in emotions:
            complete_emotion(emo)
            name = "+".join(f"{k}{v:g}" if v != 1 else k for k, v in emo.items())
            for mode in modes:
                clip_id = f"{name}__{mode}"
                beh = behaviour_for_clip(
                    setting=setting_for[mode], emotion=emo, base_dir=base_dir, seed=seed,
                    speech=speech, pad_s=lead_s, fps=fps, n_frames=n_frames,
                    weights=speech_weights, avatar=avatar,
                )  # fmt: skip
                plans[clip_id] = beh
                counts = beh.plan.layer_counts() if beh else {}
                rows[clip_id] = {
                    "clip_id": clip_id, "emotion": name, "mode": mode, "path": f"{clip_id}.mp4",
                    "duration_s": None, "fps": fps,
                    "width": settings.width, "height": settings.height,
                    "sha256": None,
                    **{f"n_{k}": counts.get(k, 0) for k in
                       ("posture", "mannerism", "gesture", "blink")},
                    "blinks_per_min": round(counts.get("blink", 0) / duration_s * 60, 2),
                }  # fmt: skip
                frames = ClipFrames(
                    clip_id=clip_id,
                    weights=speech_weights if beh is None else beh.weights,
                    poses=None if beh is None else tuple(beh.poses),
                    audio=audio, audio_sha256=audio_hash, fps=fps, settings=settings,
                    framing_sha256=framing.sha256, drawn_sha256=framing.sha256,
                )  # fmt: skip
                yield GridTask(clip_id, render_clip, (frames, framing, framing))

    def finished(clip_id: str, rendered: RenderedClip) -> None:
        info = write_clip(rendered, out=out / rows[clip_id]["path"])
        rows[clip_id].update(duration_s=round(info.duration_s, 6), sha256=info.sha256)
        beh = plans[clip_id]
        if beh is not None:
            _write_json(out / f"{clip_id}.behaviour.json", beh.log())
            fig = plan_timeline_figure(
                beh.plan, cues=cues, phones=speech.phones, offset_s=lead_s, title=f"{clip_id}",
            )  # fmt: skip
            fig.savefig(out / f"{clip_id}.timeline.png")
            plt.close(fig)
        log(f"  rendered {clip_id}: {json.dumps(beh.plan.counts()) if beh else 'none'}")

    report = render_grid(tasks(), cluster=cluster, on_result=finished, progress=progress)
    finish_grid(report, rows=list(rows.values()), out=out, log=log)
    rows = list(rows.values())
    for note in write_manifest(out, rows, columns=BEHAVIOUR_CLIP_COLUMNS, merge=True):
        log(note)
    return rows


def _top_emotion(unit: Unit) -> np.ndarray:
    best = max(unit.intensity, key=lambda e: unit.intensity[e])
    return complete_emotion({best: 1.0} if best != "neutral" else {})


def unit_sheet(
    *,
    out: Path,
    avatar: Avatar,
    library: Library | None = None,
    tile: int = 300,
    columns: int = 6,
) -> Path:
    """A PNG with one tile per unit with a motion: the face at the unit's stroke, posed for
    the emotion the unit is most intense in (eq. 5 blend), labelled with unit and layer."""
    from PIL import Image, ImageDraw

    from facelab.stimuli.render.contact_sheets import sheet_font
    from facelab.stimuli.render.scene import face_closeup

    library = library or default_library()
    units = [u for u in library.units if u.has_motion]
    if not units:
        raise BehaviourError("the library has no unit with a motion to draw")
    settings = face_closeup(avatar, size_px=tile, margin=1.5)  # room for head turns
    traits = avatar_traits(avatar)
    font = sheet_font(15)
    tiles = []
    with Renderer(avatar, settings) as renderer:
        for u in units:
            char = _top_emotion(u)
            amps = blend_pose(u, char, radius=library.rbf_radius)
            assert u.curve is not None
            value = float(curve_values(u.curve, np.array([u.curve.phase("stroke")]))[0])
            rot = np.zeros((1, len(ROTATIONS)))
            arkit = {}
            for ch, a in amps.items():
                if ch in ROTATIONS:
                    rot[0, ROTATIONS.index(ch)] = a * value
                else:
                    arkit[ch] = np.array([a * value])
            frames = BehaviourFrames(np.zeros(1), arkit, rot)
            w, poses, _ = apply_to_weights(
                frames, np.zeros((1, len(avatar.target_names)), np.float32), **traits
            )
            img = Image.fromarray(renderer.frame(w[0], pose=poses[0]))
            values = set(u.intensity.values())
            top = max(u.intensity, key=lambda e: u.intensity[e]) if len(values) > 1 else "all"
            ImageDraw.Draw(img).text(
                (8, 6), f"{u.behaviour}\n{u.layer} · {top}", fill=(255, 255, 255), font=font
            )
            tiles.append(img)
    rows = (len(tiles) + columns - 1) // columns
    sheet = Image.new("RGB", (columns * tile, rows * tile), (40, 40, 40))
    for i, t in enumerate(tiles):
        sheet.paste(t, ((i % columns) * tile, (i // columns) * tile))
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return out
