"""``facelab render``: every (stimulus, condition) clip a protocol needs, cached by content.

For each stimulus set a block (or the practice trial) uses, each stimulus is synthesised or
loaded once and analysed once; each condition's method turns the analysed track (vowel-isolated
where the stimulus asks for it) into a blendshape track, which is rendered to
``<out>/<set>__<stimulus>__<condition>.mp4``. A clip is re-rendered only when the hash of its
inputs - audio, blendshape track, avatar, method and parameters, renderer settings - changes;
the hash is kept in a JSON file beside the clip. ``clips.csv`` lists every clip (DESIGN.md).
Clips whose pictures are drawn from the same inputs - conditions alike but for their
``audio_offset_ms`` - are rendered once: the others copy that clip's video stream and get
their own (shifted) sound (:func:`~facelab.stimuli.render.clip.remux`).

The clip list and each clip's spec hash (checked by ``facelab run``) are in
:mod:`facelab.stimuli.render.clipspec`.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facelab.durable import replace_file
from facelab.errors import StageError, VisemeError
from facelab.formats import (
    TRACK_COLUMNS,
    TRACK_FORMAT,
    behaviour_log_path,
    track_path,
    write_manifest,
)
from facelab.grid import SERIAL, Cluster, GridTask, Progress
from facelab.protocol import Condition, Protocol, Stimulus
from facelab.stimuli.avatar import Avatar
from facelab.stimuli.behaviour.clip import ClipBehaviour, behaviour_for_clip, clip_seed
from facelab.stimuli.methods import DriveInput, get
from facelab.stimuli.methods.types import BlendshapeTrack
from facelab.stimuli.render.clip import (
    ClipInfo,
    frame_poses,
    frame_weights,
    padded_audio,
    remux_many,
    sha256_file,
    weights_at,
)
from facelab.stimuli.render.clipspec import (
    CLIP_COLUMNS,
    RENDER_VERSION,
    ClipJob,
    clip_spec_hash,
    plan,
)
from facelab.stimuli.render.prepare import speech_for, track_source_text, tracks_for
from facelab.stimuli.render.renderer import RenderSettings
from facelab.stimuli.render.scene import load_avatar, settings_for
from facelab.stimuli.render.sound import clip_sound
from facelab.stimuli.render.task import (
    ClipFrames,
    RenderedClip,
    audio_sha256,
    clip_track,
    finish_grid,
    render_clip,
    render_grid,
    shared_avatar,
    write_clip,
)
from facelab.stimuli.speech.audio import Phone, Speech
from facelab.stimuli.speech.track import VOWELS, VisemeTrack
from facelab.stimuli.speech.vowels import vowel_stretches

__all__ = [
    "VowelPeak",
    "build_clips",
    "clip_counts",
    "load_avatar",
    "settings_for",
    "vowel_peaks",
]


def _track_hash(track: BlendshapeTrack) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(track.times, np.float64).tobytes())
    h.update(np.ascontiguousarray(track.weights, np.float64).tobytes())
    h.update("|".join(track.names).encode())
    if track.poses is not None:
        h.update(np.ascontiguousarray(track.poses, np.float64).tobytes())
    return h.hexdigest()


def stand_in(avatar: Avatar, cond: Condition, *, base_dir: Path) -> str | None:
    """What plays in place of the condition's method on this avatar, if anything (for clip
    metadata)."""
    method = get(cond.method)
    return method.playback(avatar, cond.settings, base_dir=base_dir).stand_in


def _blendshapes(
    protocol: Protocol,
    job: ClipJob,
    speech: Speech,
    tracks: tuple[VisemeTrack, VisemeTrack | None],
    base_dir: Path,
    avatar: Avatar,
) -> BlendshapeTrack:
    cond = protocol.condition(job.condition)
    analysed, isolated = tracks
    viseme_track = (
        isolated
        if (isolated is not None and job.condition in job.stimulus.vowel_isolation)
        else analysed
    )
    inp = DriveInput(track=viseme_track, phones=speech.phones, base_dir=base_dir,
                     stimulus_set=job.stimulus_set, stimulus_id=job.stimulus.id, audio=speech)
    return get(cond.method).drive_on(avatar, inp, cond.settings)


def _behaviour(
    protocol: Protocol,
    job: ClipJob,
    speech: Speech,
    base_dir: Path,
    avatar: Avatar,
    fps: int,
    weights: np.ndarray,
) -> ClipBehaviour | None:
    cond = protocol.condition(job.condition)
    return behaviour_for_clip(
        setting=cond.behaviour,
        emotion=cond.emotion if cond.emotion is not None else job.stimulus.emotion,
        base_dir=base_dir,
        seed=clip_seed(protocol.rendering.behaviour_seed, job.stimulus_set, job.stimulus.id),
        speech=speech,
        pad_s=protocol.rendering.pad_s,
        fps=fps,
        n_frames=len(weights),
        weights=weights,
        avatar=avatar,
    )


def _modality(protocol: Protocol, cond: Condition) -> str | None:
    """What of a clip's hashed inputs the modality changes (None: audiovisual, as before)."""
    if cond.modality == "audiovisual":
        return None
    if cond.modality == "audio_only":
        return f"audio_only/{protocol.rendering.audio_only_face}"
    return cond.modality


def _behaviour_hash(behaviour: ClipBehaviour) -> str:
    """SHA-256 of the plan and of what realising it gave: the weights and poses drawn (so a
    change in how a plan is realised - e.g. the lid limit - re-renders the clip)."""
    h = hashlib.sha256(
        json.dumps(behaviour.plan.to_json(), sort_keys=True, ensure_ascii=False).encode("utf-8")
    )
    h.update(np.ascontiguousarray(behaviour.weights, dtype=np.float32).tobytes())
    h.update(repr(behaviour.poses).encode())
    return h.hexdigest()


def _write_json(path: Path, data: dict, *, indent: int = 1, ascii_only: bool = False) -> None:
    replace_file(path, json.dumps(data, indent=indent, ensure_ascii=ascii_only) + "\n")


def build_clips(
    protocol: Protocol,
    *,
    protocol_path: Path,
    out: Path,
    settings: RenderSettings | None = None,
    fps: int | None = None,
    cluster: Cluster = SERIAL,
    progress: Progress | None = None,
    log: Callable[[str], None] = print,
) -> list[dict]:
    """Render (or reuse) every clip - here, or on the Dask ``cluster`` - and write
    ``out/clips.csv``; return its rows. Every method is driven here; workers get each clip's
    frame weights, poses and audio (:mod:`facelab.stimuli.render.task`). Clips that fail are
    listed in one StageError after the others are written (no ``clips.csv`` then);
    ``progress(clip_id, event, done, failed, retried)`` is called per clip (event ``reused``
    for a clip whose file already matches)."""
    base_dir = protocol_path.parent
    settings = settings or settings_for(protocol)
    fps = fps or protocol.rendering.fps
    avatar = load_avatar(protocol, base_dir=base_dir)
    avatar_ref = shared_avatar(avatar)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    waiting: dict[str, tuple[dict, dict, ClipBehaviour | None]] = {}
    cache: dict[str, tuple[Speech, tuple[VisemeTrack, VisemeTrack | None]]] = {}
    pending_tracks: dict[str, bytes] = {}
    videos: dict[str, str] = {}  # picture key -> the clip whose video it is
    remuxed: list[tuple[dict, dict, ClipBehaviour | None, bytes, Speech, str, int]] = []
    reused = 0

    spectra: dict[str, np.ndarray] = {}  # stimulus set -> its speech's long-term spectrum

    def speech_of(set_id: str, stim: Stimulus) -> Speech:
        key_stim = f"{set_id}/{stim.id}"
        if key_stim not in cache:
            speech = speech_for(stim, base_dir=base_dir,
                                sample_rate=protocol.rendering.audio_sample_rate)  # fmt: skip
            cache[key_stim] = (speech, tracks_for(stim, speech))
        return cache[key_stim][0]

    def tasks() -> Iterator[GridTask]:
        nonlocal reused
        for job in plan(protocol):
            speech_of(job.stimulus_set, job.stimulus)
            speech, tracks = cache[f"{job.stimulus_set}/{job.stimulus.id}"]
            bs = _blendshapes(protocol, job, speech, tracks, base_dir, avatar)
            cond = protocol.condition(job.condition)
            audio = padded_audio(speech, pad_s=protocol.rendering.pad_s)
            n_frames = round(audio.duration_s * fps)
            weights = frame_weights(
                bs, avatar, fps=fps, n_frames=n_frames, pad_s=protocol.rendering.pad_s
            )
            modality = _modality(protocol, cond)
            behaviour = None
            if cond.modality == "audio_only":  # the voice with a still face (or none)
                weights = np.zeros_like(weights)
                bs = replace(bs, poses=None)
            else:
                behaviour = _behaviour(protocol, job, speech, base_dir, avatar, fps, weights)
            key = hashlib.sha256(
                json.dumps(
                    {
                        "version": RENDER_VERSION,
                        "audio": hashlib.sha256(audio.samples.tobytes()).hexdigest(),
                        "sample_rate": audio.sample_rate,
                        "track": _track_hash(bs),
                        "avatar": avatar_ref.sha256,
                        "method": cond.method,
                        "params": cond.params,
                        "settings": settings.__dict__,
                        "fps": fps,
                        "pad_s": protocol.rendering.pad_s,
                        "track_format": TRACK_FORMAT,  # drawn from the track's float32 values
                        **({"modality": modality} if modality else {}),
                        **(
                            {"behaviour": _behaviour_hash(behaviour)}
                            if behaviour is not None
                            else {}
                        ),
                    },
                    sort_keys=True,
                    default=str,
                ).encode()
            ).hexdigest()
            video_key = key  # what the picture is drawn from: clips alike but for their sound
            offset_ms = cond.audio_offset_ms
            shown_audio, mix = clip_sound(protocol, job, audio, base_dir=base_dir,
                                          spectra=spectra, speech_of=speech_of)  # fmt: skip
            if offset_ms or mix is not None:  # the same picture, its own sound
                heard = f"{video_key} sound={audio_sha256(shown_audio)}"
                key = hashlib.sha256(heard.encode()).hexdigest()
            spec = clip_spec_hash(protocol, job, base_dir=base_dir)
            mp4 = out / f"{job.clip_id}.mp4"
            meta = out / f"{job.clip_id}.json"
            # the head: the behaviour layer's, else the method's own (a capture's angles)
            poses = None if behaviour is None else behaviour.poses
            if poses is None and bs.poses is not None:
                poses = frame_poses(bs, fps=fps, n_frames=len(weights),
                                    pad_s=protocol.rendering.pad_s)  # fmt: skip
            elif bs.poses is not None:
                bs.notes["angles_not_played"] = "the behaviour layer turns the head"
            track, drawn, poses = clip_track(
                clip_id=job.clip_id, avatar=avatar, avatar_sha256=avatar_ref.sha256,
                weights=weights if behaviour is None else behaviour.weights,
                poses=poses, fps=fps,
                sample_rate=audio.sample_rate,
                speech_start_s=protocol.rendering.pad_s + offset_ms / 1000.0,
            )  # fmt: skip
            track_file = track_path(out, job.clip_id)
            row = {
                "clip_id": job.clip_id,
                "stimulus_set": job.stimulus_set,
                "stimulus": job.stimulus.id,
                "condition": job.condition,
                "path": mp4.name,
                "duration_s": None,
                "fps": fps,
                "width": settings.width,
                "height": settings.height,
                "sha256": None,
                "spec_sha256": spec,
                "status": "rendered",
                "track_file": track_file.name,
                "track_sha256": hashlib.sha256(track).hexdigest(),
            }
            rows.append(row)
            video_source = videos.setdefault(video_key, job.clip_id)
            if mp4.exists() and meta.exists():
                saved = json.loads(meta.read_text())
                if (
                    saved.get("input_hash") == key
                    and saved.get("spec_sha256") == spec
                    and saved.get("sha256") == sha256_file(mp4)
                ):
                    if not track_file.is_file() or sha256_file(track_file) != row["track_sha256"]:
                        replace_file(track_file, track)  # the clip was drawn from these
                    row.update(
                        duration_s=round(saved["duration_s"], 6),
                        sha256=saved["sha256"],
                        status="unchanged",
                    )
                    reused += 1
                    log(f"  unchanged {job.clip_id} (reused)")
                    if progress is not None:
                        progress(job.clip_id, "reused", reused, 0, 0)
                    continue
            note = stand_in(avatar, cond, base_dir=base_dir)
            about = {
                "input_hash": key,
                "spec_sha256": spec,
                "method": cond.method,
                "params": cond.params,
                "track_source": track_source_text(job.stimulus),
                # audio-only analysis: the mel-filter warp its search chose (1 = as trained)
                **(
                    {"analysis_warp": tracks[0].warp}
                    if job.stimulus.track_source == "audio"
                    else {}
                ),
                "avatar": avatar.name,
                "avatar_kind": avatar.source.get("kind", "unknown"),
                "stand_in": note,
                "modality": cond.modality,
                **(
                    {"audio_only_face": protocol.rendering.audio_only_face}
                    if cond.modality == "audio_only"
                    else {}
                ),
                **({"audio_offset_ms": offset_ms} if offset_ms else {}),
                **({"noise": mix.to_json()} if mix is not None else {}),
                **({"track_notes": bs.notes} if bs.notes else {}),
                **({"behaviour": behaviour.summary()} if behaviour is not None else {}),
            }
            if video_source != job.clip_id:  # its picture is another clip's: re-muxed later
                about["video_from"] = video_source
                remuxed.append((row, about, behaviour, track, shown_audio, video_source,
                                len(drawn)))  # fmt: skip
                continue
            waiting[job.clip_id] = (row, about, behaviour)
            pending_tracks[job.clip_id] = track
            frames = ClipFrames(
                clip_id=job.clip_id,
                weights=drawn,
                poses=poses,
                audio=shown_audio,
                audio_sha256=audio_sha256(shown_audio),
                blank=cond.modality == "audio_only"
                and protocol.rendering.audio_only_face == "none",
                fps=fps,
                settings=settings,
                framing_sha256=avatar_ref.sha256,
                drawn_sha256=avatar_ref.sha256,
            )
            yield GridTask(job.clip_id, render_clip, (frames, avatar_ref, avatar_ref))

    def finished(clip_id: str, rendered: RenderedClip) -> None:
        row, about, behaviour = waiting.pop(clip_id)
        replace_file(out / row["track_file"], pending_tracks.pop(clip_id))
        info = write_clip(rendered, out=out / row["path"])
        written(row, about, behaviour, info)
        note = about["stand_in"]
        log(f"  rendered {clip_id} ({info.frames} frames)" + (f"; {note}" if note else ""))

    def written(row: dict, about: dict, behaviour: ClipBehaviour | None, info: ClipInfo) -> None:
        clip_id = row["clip_id"]
        row.update(duration_s=round(info.duration_s, 6), sha256=info.sha256)
        _write_json(
            out / f"{clip_id}.json",
            {
                "input_hash": about["input_hash"],
                "spec_sha256": about["spec_sha256"],
                "sha256": info.sha256,
                "track_sha256": row["track_sha256"],
                "frames": info.frames,
                "duration_s": info.duration_s,
                **{k: v for k, v in about.items() if k not in ("input_hash", "spec_sha256")},
            },
            indent=2,
            ascii_only=True,
        )
        if behaviour is not None:
            _write_json(behaviour_log_path(out, clip_id), behaviour.log())

    report = render_grid(tasks(), cluster=cluster, on_result=finished, progress=progress)
    # the clips sharing a picture re-muxed together (one ffmpeg for several sounds)
    by_picture: dict[tuple[str, int], list[tuple]] = {}
    for entry in remuxed:
        by_picture.setdefault((entry[5], entry[6]), []).append(entry)
    for (source, n_frames), group in by_picture.items():
        if source in report.failed:
            for entry in group:
                report.failed[entry[0]["clip_id"]] = f"its picture is {source}'s, which failed"
            continue
        try:
            infos = remux_many(video=out / f"{source}.mp4", fps=fps, n_frames=n_frames,
                               outputs=[(e[4], out / e[0]["path"]) for e in group])  # fmt: skip
        except StageError as exc:
            for entry in group:
                report.failed[entry[0]["clip_id"]] = str(exc)
            continue
        for (row, about, behaviour, track, _audio, _source, _n), info in zip(
            group, infos, strict=True
        ):
            replace_file(out / row["track_file"], track)
            written(row, about, behaviour, info)
            row["status"] = "remuxed"
            log(f"  re-muxed {row['clip_id']} (the picture of {source}, the voice "
                f"{about.get('audio_offset_ms', 0.0):+g} ms)")
    finish_grid(report, rows=rows, out=out, log=log)
    write_manifest(out, rows, columns=(*CLIP_COLUMNS, *TRACK_COLUMNS))
    return rows


def clip_counts(rows: list[dict]) -> str:
    """How the clips of a render came about, for the command's summary line."""
    n = {k: sum(r["status"] == k for r in rows) for k in ("rendered", "remuxed", "unchanged")}
    remuxed = f"{n['remuxed']} re-muxed (another clip's picture, their own sound), " if n[
        "remuxed"] else ""  # fmt: skip
    return f"{len(rows)} clips ({n['rendered']} rendered, {remuxed}{n['unchanged']} reused)"


@dataclass(frozen=True)
class VowelPeak:
    """One condition's face at one vowel's peak in the protocol's vowel stimulus."""

    condition: str
    vowel: str
    t: float  # s from the speech's start (the clip adds rendering.pad_s before it)
    window: np.ndarray  # (7, n_targets) the avatar's target weights every 1/30 s, t ± 0.1 s

    @property
    def weights(self) -> np.ndarray:
        """(n_targets,) the weights at t (the window's middle)."""
        return self.window[len(self.window) // 2]


def vowel_peaks(protocol: Protocol, *, base_dir: Path, avatar: Avatar) -> list[VowelPeak]:
    """Every condition's target weights at each vowel's peak of the first stimulus with
    ``expected_vowels`` (for contact sheets and articulation checks). Raises StageError when
    the protocol has no such stimulus or its vowels are not found in the track."""
    stim_set, stim = next(
        ((s.id, st) for s in protocol.stimulus_sets for st in s.stimuli if st.expected_vowels),
        (None, None),
    )
    if stim is None or stim_set is None:
        raise StageError("no stimulus gives expected_vowels: no vowel peaks to show")
    speech = speech_for(stim, base_dir=base_dir, sample_rate=protocol.rendering.audio_sample_rate)
    tracks = tracks_for(stim, speech)
    times = vowel_peak_times(stim, tracks[0], where=f"{stim_set}/{stim.id}",
                             phones=speech.phones)  # fmt: skip
    offsets = np.arange(-3, 4) / 30.0
    peaks = []
    for cond in protocol.conditions:
        job = ClipJob("", stim_set, stim, cond.id)
        bs = _blendshapes(protocol, job, speech, tracks, base_dir, avatar)
        for vowel, centre in times:
            window = np.stack([weights_at(bs, avatar, t=centre + dt) for dt in offsets])
            peaks.append(VowelPeak(cond.id, vowel, centre, window))
    return peaks


def vowel_peak_times(
    stim: Stimulus, analysed: VisemeTrack, *, where: str, phones: Sequence[Phone] = ()
) -> list[tuple[str, float]]:
    """(vowel, s from the speech's start) at each peak of ``stim.expected_vowels`` in its
    analysed track (the frame where the vowel's own weight is highest within its stretch:
    :func:`~facelab.stimuli.speech.vowels.vowel_stretches`, by the words' ``phones`` when the
    vowels run together). StageError when the stretches found are not one per vowel."""
    vowels = stim.expected_vowels or ""
    try:
        segments = vowel_stretches(analysed, vowels=vowels, phones=phones)
    except VisemeError as exc:
        raise StageError(f"stimulus {where}: {exc}") from None
    out = []
    for (a, b), vowel in zip(segments, vowels, strict=True):
        x = analysed.vowels()[a:b, VOWELS.index(vowel)]
        out.append((vowel, float(analysed.times[a + int(np.argmax(x))])))
    return out
