"""``facelab latency-test``: a set-up's audio-video offset measured with a photodiode and a
microphone - the test clip, its playback in the lab window, the recording's measurement."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    force_option,
    output_dir,
    output_file,
    parse_size,
    real,
    verbs,
    whole,
)


def _cmd_latency_test(args: argparse.Namespace) -> int:
    return {"clip": _clip, "play": _play, "measure": _measure}[args.action](args)


def _clip(args: argparse.Namespace) -> int:
    from facelab.stimuli.render.latency_test_clip import LatencyTestClip, write_latency_test_clip

    out = output_file(args.out, option="--out", force=args.force)
    if out.suffix.lower() != ".mp4":
        raise FacelabError(f"--out {out}: expected a .mp4 file name")
    output_file(out.with_suffix(".json"), option="--out (its schedule)", force=args.force)
    width, height = parse_size(args.size) or (1280, 720)
    clip = LatencyTestClip.plan(
        fps=args.fps, width=width, height=height, events=args.events,
        period_s=args.period_ms / 1000, flash_frames=args.flash_frames, tone_hz=args.tone_hz,
    )  # fmt: skip
    info = write_latency_test_clip(clip, out=out)
    print(f"wrote {info.path} ({clip.events} flashes with tone bursts, every "
          f"{1000 * clip.period_s:.0f} ms, {info.duration_s:.1f} s, {clip.fps} frames/s) and "
          f"{out.with_suffix('.json')}")  # fmt: skip
    print("  tape the photodiode over the outlined square (lower left); record it and a "
          "microphone at the participant's head as two channels of one recording")  # fmt: skip
    return 0


def _play(args: argparse.Namespace) -> int:
    from facelab.experiment.preflight import ClipRef
    from facelab.experiment.window import Window
    from facelab.hashing import sha256_file
    from facelab.protocol import load_protocol
    from facelab.stimuli.render.latency_test_clip import LatencyTestClip

    protocol = load_protocol(args.protocol)
    clip_path = Path(args.clip)
    if not clip_path.is_file():
        raise FacelabError(f"{clip_path}: clip not found (write it with facelab latency-test clip)")
    clip = LatencyTestClip.read(clip_path.with_suffix(".json"))
    if args.size and not args.windowed:
        raise FacelabError("--size goes with --windowed")
    size = parse_size(args.size, largest=None) or (1280, 800)  # a window
    ref = ClipRef(path=clip_path, sha256=sha256_file(clip_path), duration_s=clip.duration_s,
                  fps=clip.fps, size=(clip.width, clip.height))  # fmt: skip
    json_out = output_file(args.json, option="--json", force=args.force) if args.json else None
    fullscreen = protocol.presentation.fullscreen and not args.windowed
    rows = []
    with Window(protocol, clips={}, size=size, fullscreen=fullscreen) as window:
        screen = {"gl_renderer": window.gl_renderer, "paced_hz": window.paced_hz}
        for k in range(args.repeat):
            shown = window.play_file(ref)
            rows.append({
                "playing": k + 1, "frames_expected": shown.frames_expected,
                "frames_dropped": shown.dropped, "flips": len(shown.flip_times),
            })  # fmt: skip
            print(f"playing {k + 1}/{args.repeat}: {len(shown.flip_times)} flips, "
                  f"{shown.dropped} of {shown.frames_expected} frames not shown")  # fmt: skip
    if json_out is not None:
        json_out.write_text(json.dumps({"clip": str(clip_path), "window": size, **screen,
                                               "playings": rows}, indent=2) + "\n",
                                   encoding="utf-8")  # fmt: skip
    return 0


def _measure(args: argparse.Namespace) -> int:
    import soundfile as sf

    from facelab.analysis.latency_recording import measure_latency
    from facelab.stimuli.render.latency_test_clip import LatencyTestClip

    path = Path(args.recording)
    if not path.is_file():
        raise FacelabError(f"{path}: recording not found")
    try:
        data, rate = sf.read(str(path), dtype="float32", always_2d=True)
    except (sf.LibsndfileError, RuntimeError, TypeError, ValueError):
        raise FacelabError(f"{path}: not a readable WAV/FLAC recording") from None
    schedule = LatencyTestClip.read(Path(args.schedule))
    out = output_dir(args.out, option="--out") if args.out else None
    if out is not None and out.is_dir():
        for name in ("latency_events.csv", "latency_summary.json"):
            output_file(out / name, option="--out", force=args.force)
    got = measure_latency(
        data, sample_rate=int(rate), photodiode=args.photodiode_channel, mic=args.mic_channel,
        period_s=schedule.period_s, tone_hz=schedule.tone_hz, expected=schedule.events,
        source=str(path),
    )  # fmt: skip
    s = got.summary
    print(f"{s['pairs']} of {s['events_expected']} events measured ({s['flashes_found']} "
          f"flashes, {s['tone_bursts_found']} tone bursts found)")  # fmt: skip
    print(f"sound after light: mean {s['offset_ms_mean']:.1f} ms, SD {s['offset_ms_sd']:.1f}, "
          f"median {s['offset_ms_median']:.1f}, range {s['offset_ms_min']:.1f} to "
          f"{s['offset_ms_max']:.1f} ms (positive: the sound late)")  # fmt: skip
    if s["light_interval_error_ms_max"] is not None:
        frame_ms = 1000 / schedule.fps
        print(f"flash intervals off the schedule by up to {s['light_interval_error_ms_max']:.1f}"
              f" ms (a frame at {schedule.fps} frames/s is {frame_ms:.1f} ms)")  # fmt: skip
    if s["flashes_missing"]:
        print(f"warning: {s['flashes_missing']} flashes of {schedule.events} not found "
              "(frames dropped, or the recording started late or ended early)")  # fmt: skip
    for warning in s["warnings"]:
        print(f"warning: {warning}")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        got.events.to_csv(out / "latency_events.csv", index=False)
        (out / "latency_summary.json").write_text(
            json.dumps({"recording": str(path), **s}, indent=2) + "\n", encoding="utf-8"
        )
        print(f"wrote {out / 'latency_events.csv'} and {out / 'latency_summary.json'}")
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add("latency-test", "a set-up's audio-video offset measured with a photodiode and a "
            "microphone: the test clip, its playback, the recording's measurement",
            _cmd_latency_test)  # fmt: skip
    verb = verbs(p)
    v = verb("clip", "write the test clip (flashes and tone bursts that start together) and "
             "its schedule (.json beside it)")  # fmt: skip
    v.add_argument("--out", required=True, metavar="CLIP.mp4")
    v.add_argument("--fps", type=whole(lo=10, hi=240), default=60,
                   help="frames per second (default 60; the study's display rate)")  # fmt: skip
    v.add_argument("--size", metavar="WxH", help="default 1280x720")
    v.add_argument("--events", type=whole(lo=3, hi=1000), default=20,
                   help="flashes (default 20)")  # fmt: skip
    v.add_argument("--period-ms", type=real(above=0), default=1000.0,
                   help="time between flashes (default 1000)")  # fmt: skip
    v.add_argument("--flash-frames", type=whole(lo=1, hi=60), default=3,
                   help="frames each flash lasts (default 3)")  # fmt: skip
    v.add_argument("--tone-hz", type=real(above=0), default=1000.0,
                   help="the tone's frequency (default 1000)")  # fmt: skip
    force_option(v)

    v = verb("play", "play the test clip in the lab window, as facelab run plays the study's "
             "clips")  # fmt: skip
    v.add_argument("protocol", metavar="PROTOCOL", help="the study (its window settings)")
    v.add_argument("clip", metavar="CLIP.mp4")
    v.add_argument("--repeat", type=whole(lo=1, hi=100), default=1, help="times to play it")
    v.add_argument("--windowed", action="store_true", help="a window instead of full screen")
    v.add_argument("--size", metavar="WxH", help="window size with --windowed (default 1280x800)")
    v.add_argument("--json", metavar="FILE", help="write what each playing showed")
    force_option(v)

    v = verb("measure", "measure a photodiode + microphone recording of the test clip")
    v.add_argument("recording", metavar="RECORDING.wav")
    v.add_argument("--schedule", required=True, metavar="CLIP.json",
                   help="the schedule written beside the clip")  # fmt: skip
    v.add_argument("--photodiode-channel", type=whole(lo=0), default=0,
                   help="the photodiode's channel, from 0 (default 0)")  # fmt: skip
    v.add_argument("--mic-channel", type=whole(lo=0), default=1,
                   help="the microphone's channel (default 1)")  # fmt: skip
    v.add_argument("--out", metavar="DIR", help="write latency_events.csv and "
                   "latency_summary.json here")  # fmt: skip
    force_option(v)
