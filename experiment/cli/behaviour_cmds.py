"""``facelab behaviour``: emotional non-verbal behaviour (seed 003, EMBOS) - fit a library
from annotations, plan a clip's behaviour, render demonstration clips, draw the units."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    GridProgress,
    check_options,
    cluster_of,
    cluster_options,
    figure_suffixes,
    force_option,
    output_dir,
    output_file,
    parse_size,
    picture_suffixes,
    real,
    say_checks,
    seed,
    verbs,
    whole,
)

__all__ = ["register"]


def _library(path: str | None):
    from facelab.stimuli.behaviour.library import default_library, load_library

    return default_library() if path in (None, "default") else load_library(Path(path))


def _fit(args: argparse.Namespace) -> int:
    from facelab.stimuli.behaviour.fit import fit_library, format_report, read_annotations

    if not args.input or not args.out:
        raise FacelabError("facelab behaviour fit ANNOTATIONS --out LIBRARY.json")
    out = output_file(args.out, option="--out", force=args.force)
    table = read_annotations(Path(args.input))
    library, stats = fit_library(table, alpha=args.alpha)
    missing: list[str] = []
    if args.motions != "none":
        library, missing = library.with_motions(_library(args.motions))
    out.write_text(
        json.dumps(library.model_dump(mode="json", exclude_defaults=False), indent=1,
                   ensure_ascii=False) + "\n",
        encoding="utf-8",
    )  # fmt: skip
    report = format_report(stats, source=str(args.input), alpha=args.alpha)
    if missing:
        report += (
            "\nNo motion (channels, curve) for: " + ", ".join(missing) + " - they are kept "
            "with their statistics but not planned until a motion library names them.\n"
        )
    report_path = Path(args.report) if args.report else out.with_suffix(".report.md")
    report_path.write_text(report, encoding="utf-8")
    print(
        f"fitted {len(library.units)} units from {len(table)} annotations "
        f"({table['emotion'].nunique()} emotions) -> {out}; report {report_path}"
    )
    if missing:
        print(f"  no motion for: {', '.join(missing)}")
    return 0


def _cues(args: argparse.Namespace, pad_s: float):
    from facelab.stimuli.behaviour.plan import SpeechCues

    if args.text and args.stimulus:
        raise FacelabError("give --text or --stimulus, not both")
    if args.text:
        from facelab.stimuli.speech.tts import synthesize

        speech = synthesize(args.text)
        return speech, SpeechCues.from_speech(speech, offset_s=pad_s)
    if args.stimulus:
        from facelab.protocol import load_protocol
        from facelab.resources import protocol_path
        from facelab.stimuli.render.prepare import find_stimulus, speech_for

        # without --protocol: the shipped seed-003 protocol's stimuli
        path = Path(args.protocol) if args.protocol else protocol_path("hattori_behaviour")
        protocol = load_protocol(path)
        _, stim = find_stimulus(protocol, args.stimulus)
        speech = speech_for(
            stim, base_dir=path.parent, sample_rate=protocol.rendering.audio_sample_rate
        )
        return speech, SpeechCues.from_speech(speech, offset_s=pad_s)
    return None, SpeechCues()


def _timeline(path: Path):
    """``[{"time_s": 0, "joy": 0.8}, {"time_s": 5, "sadness": 0.6}, …]`` -> a timeline
    (the shape a protocol's ``emotion:`` timeline has)."""
    import math

    from facelab.stimuli.behaviour.clip import emotion_timeline
    from facelab.textfiles import read_json

    shape = '[{"time_s": 0, "joy": 0.8}, {"time_s": 5, "sadness": 0.6}, …]'
    keys = read_json(path, what="--emotion-timeline", error=FacelabError)
    if not isinstance(keys, list) or not keys:
        raise FacelabError(f"--emotion-timeline {path}: expected a JSON list of keys, {shape}")
    for i, key in enumerate(keys, start=1):
        numbers = isinstance(key, dict) and all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in key.values()
        )  # fmt: skip
        if not numbers or "time_s" not in key:
            raise FacelabError(
                f"--emotion-timeline {path}: key {i} is "
                f"{json.dumps(key, ensure_ascii=False)[:80]}; expected a time_s and emotion "
                f"values, all numbers, e.g. {shape}"
            )
    try:
        return emotion_timeline(keys)
    except ValueError as exc:
        raise FacelabError(f"--emotion-timeline {path}: {exc}") from None


def _plan(args: argparse.Namespace) -> int:
    from facelab.stimuli.behaviour.clip import layers_for
    from facelab.stimuli.behaviour.plan import EmotionTimeline, parse_emotion, plan_behaviour

    if not (args.emotion or args.emotion_timeline) or not args.out or args.duration_s is None:
        raise FacelabError(
            "facelab behaviour plan (--emotion joy=0.8 | --emotion-timeline KEYS.json) "
            "(--text T | --stimulus SET/ID --protocol P) --duration-s S --seed N --out PLAN.json"
        )
    if args.emotion_timeline:
        emotion = _timeline(Path(args.emotion_timeline))
    elif len(args.emotion) != 1:
        raise FacelabError("plan: give one --emotion (e.g. joy=0.5,surprise=0.3)")
    else:
        emotion = EmotionTimeline.constant(parse_emotion(args.emotion[0]))
    out = output_file(args.out, option="--out", force=args.force)
    # every file the plan writes checked before the first is written
    bml = output_file(args.bml, option="--bml", force=args.force) if args.bml else None
    fig_path = (output_file(args.figure, option="--figure", force=args.force,
                            suffixes=figure_suffixes) if args.figure else None)  # fmt: skip
    library = _library(args.library)
    speech, cues = _cues(args, args.lead_s)
    layers, neutral = layers_for(args.mode)
    plan = plan_behaviour(
        library,
        emotion=emotion,
        duration_s=args.duration_s,
        seed=args.seed,
        cues=cues,
        layers=layers,
        neutral_layers=neutral,
    )
    out.write_text(json.dumps(plan.to_json(), indent=1, ensure_ascii=False) + "\n", "utf-8")
    print(f"{len(plan.events)} events over {args.duration_s:g} s -> {out}")
    print("  " + ", ".join(f"{k} {v}" for k, v in plan.counts().items()))
    if bml is not None:
        bml.write_text(plan.to_bml(library), encoding="utf-8")
        print(f"  BML 1.0 -> {bml}")
    if fig_path is not None:
        import matplotlib.pyplot as plt

        from facelab.stimuli.render.plots import plan_timeline_figure

        fig = plan_timeline_figure(
            plan,
            cues=cues,
            phones=speech.phones if speech is not None else (),
            offset_s=args.lead_s,
            title=out.stem,
        )
        fig.savefig(fig_path)
        plt.close(fig)
        print(f"  timeline -> {fig_path}")
    for note in plan.notes:
        print(f"  note: {note}")
    return 0


def _render(args: argparse.Namespace) -> int:
    from facelab.stimuli.avatar import default_head, load
    from facelab.stimuli.behaviour.plan import parse_emotion
    from facelab.stimuli.checks.clip_set_checks import behaviour_rows, check_clip_set
    from facelab.stimuli.render.behaviour_clips import render_behaviour_clips
    from facelab.stimuli.render.renderer import RenderSettings

    if not args.text or not args.out or not args.emotion:
        raise FacelabError(
            "facelab behaviour render --text T --emotion joy=0.8 [--emotion …] --out DIR"
        )
    out = output_dir(args.out, option="--out")
    size = parse_size(args.size) or (1280, 720)
    avatar = load(Path(args.avatar)) if args.avatar else default_head()
    progress = GridProgress(quiet=False, prefix="render")
    progress.start(len(args.emotion) * len(args.modes))
    try:
        rows = render_behaviour_clips(
            text=args.text,
            emotions=[parse_emotion(e) for e in args.emotion],
            modes=args.modes,
            duration_s=args.duration_s or 30.0,
            seed=args.seed,
            out=out,
            avatar=avatar,
            settings=RenderSettings(width=size[0], height=size[1], msaa=args.msaa),
            fps=args.fps,
            lead_s=args.lead_s,
            library=args.library or "default",
            cluster=cluster_of(args),
            progress=progress,
        )
    finally:
        progress.close()
    print(f"wrote {len(rows)} clips with event logs and timelines, and clips.csv into {out}")
    report = check_clip_set(clips_dir=out, clips=rows, accept=args.accept_check,
                            extra=behaviour_rows(rows, avatar=avatar, clips_dir=out))  # fmt: skip
    say_checks(report)
    if report.failures:
        raise report.error()
    return 0


def _sheet(args: argparse.Namespace) -> int:
    from facelab.stimuli.avatar import default_head, load
    from facelab.stimuli.render.behaviour_clips import unit_sheet

    if not args.out:
        raise FacelabError("facelab behaviour sheet --out SHEET.png")
    out = output_file(args.out, option="--out", force=args.force, suffixes=picture_suffixes)
    avatar = load(Path(args.avatar)) if args.avatar else default_head()
    unit_sheet(out=out, avatar=avatar, library=_library(args.library))
    print(f"contact sheet of the library's units -> {out}")
    return 0


def _synth(args: argparse.Namespace) -> int:
    from facelab.stimuli.behaviour.synth import synthetic_annotations

    if not args.out:
        raise FacelabError("facelab behaviour synth --out ANNOTATIONS.csv")
    out = output_file(args.out, option="--out", force=args.force)
    table = synthetic_annotations(
        library=_library(args.library), seconds=args.duration_s or 120.0, seed=args.seed
    )
    table.to_csv(out, index=False)
    print(
        f"wrote {len(table)} SYNTHETIC annotations ({table['emotion'].nunique()} emotions, "
        f"planned from the library, not people) to {out}"
    )
    return 0


def _cmd_behaviour(args: argparse.Namespace) -> int:
    actions = {"fit": _fit, "plan": _plan, "render": _render, "sheet": _sheet, "synth": _synth}
    return actions[args.action](args)


def register(add: AddCommand) -> None:
    """Add this family's subcommands: one verb each, with its own options."""
    p = add(
        "behaviour",
        "emotional non-verbal behaviour (seed 003): fit a unit library from annotations, plan "
        "a clip's behaviour (JSON, BML, timeline), render demonstration clips, draw the units",
        _cmd_behaviour,
    )
    verb = verbs(p)

    def library(v: argparse.ArgumentParser) -> None:
        v.add_argument("--library", metavar="FILE", help="a behaviour library (default: shipped)")

    def emotions(v: argparse.ArgumentParser, repeat: str, *, required: bool = False) -> None:
        v.add_argument("--emotion", action="append", metavar="E", required=required,
                       help=f"e.g. joy=0.8 or joy=0.5,surprise=0.3{repeat}")  # fmt: skip

    v = verb("fit", "a unit library from an annotation table (eqs. 2-4)")
    v.add_argument(
        "input", metavar="ANNOTATIONS",
        help="a table emotion,layer,behaviour,start_s,end_s (CSV) or an ELAN .eaf",
    )  # fmt: skip
    v.add_argument("--out", required=True, metavar="LIBRARY.json")
    v.add_argument("--alpha", type=real(lo=0, hi=1), default=0.3, help="eq. 2's alpha (0.3)")
    v.add_argument("--motions", default="default", metavar="FILE",
                   help="take channels/curves/triggers of same-named units from this library "
                   "(default: the shipped one; 'none' to skip)")  # fmt: skip
    v.add_argument("--report", metavar="MD", help="report path (default LIBRARY.report.md)")
    force_option(v)

    v = verb("plan", "a behaviour plan: events with scores, as JSON, BML 1.0 and a timeline")
    library(v)
    emotions(v, "")
    v.add_argument(
        "--emotion-timeline", metavar="JSON",
        help='emotion keys over time, [{"time_s": 0, "joy": 0.8}, …] (linear between)',
    )  # fmt: skip
    v.add_argument("--text", metavar="TEXT", help="Japanese text (OpenJTalk)")
    v.add_argument("--stimulus", metavar="SET/ID", help="a stimulus of --protocol")
    v.add_argument(
        "--protocol", metavar="PROTOCOL",
        help="the protocol of --stimulus (default: the shipped hattori_behaviour)",
    )  # fmt: skip
    v.add_argument("--duration-s", type=real(above=0, hi=3600), metavar="S",
                   help="seconds (at most 3600)")
    v.add_argument("--seed", type=seed, default=1, help="seed of the plan")
    v.add_argument("--mode", choices=["gestures_only", "neutral_composite", "composite"],
                   default="composite", help="the layers planned from the emotion")  # fmt: skip
    v.add_argument("--lead-s", type=real(lo=0), default=0.5, help="silence before speech")
    v.add_argument("--out", required=True, metavar="PLAN.json")
    v.add_argument("--bml", metavar="XML", help="also write BML 1.0")
    v.add_argument("--figure", metavar="PNG", help="a timeline figure")
    force_option(v)

    v = verb("render", "demonstration clips with event logs and timelines")
    library(v)
    check_options(v)
    emotions(v, " (repeat: one clip per emotion and mode)", required=True)
    v.add_argument("--text", required=True, metavar="TEXT", help="Japanese text (OpenJTalk)")
    v.add_argument("--modes", nargs="+", default=["gestures_only", "composite"], metavar="MODE",
                   help="behaviour modes per emotion (none gestures_only neutral_composite "
                   "composite)")  # fmt: skip
    v.add_argument("--duration-s", type=real(above=0, hi=3600), metavar="S",
                   help="seconds (default 30, at most 3600)")
    v.add_argument("--seed", type=seed, default=1, help="seed of the plans")
    v.add_argument("--lead-s", type=real(lo=0), default=0.5, help="silence before speech")
    v.add_argument("--size", metavar="WxH", help="default 1280x720")
    v.add_argument("--fps", type=whole(lo=1, hi=240), default=30)
    v.add_argument("--msaa", type=int, choices=[1, 2, 4, 8], default=4)
    v.add_argument("--avatar", metavar="FILE", help="an avatar (default head)")
    v.add_argument("--out", required=True, metavar="DIR",
                   help="clip folder (clips of other emotions already there are kept)")  # fmt: skip
    cluster_options(v)

    v = verb("sheet", "every unit of a library drawn on the head")
    library(v)
    v.add_argument("--avatar", metavar="FILE", help="an avatar (default head)")
    v.add_argument("--out", required=True, metavar="PNG")
    force_option(v)

    v = verb("synth", "a SYNTHETIC annotation table planned from a library")
    library(v)
    v.add_argument("--duration-s", type=real(above=0, hi=3600), metavar="S",
                   help="seconds (at most 3600)")
    v.add_argument("--seed", type=seed, default=1, help="seed of the table")
    v.add_argument("--out", required=True, metavar="ANNOTATIONS.csv")
    force_option(v)
