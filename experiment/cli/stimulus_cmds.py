"""Stimulus commands: ``render``, ``track``, ``measure-z``, ``bench``."""

from __future__ import annotations

import argparse
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    GridProgress,
    check_options,
    cluster_of,
    cluster_options,
    deprecated,
    figure_suffixes,
    force_option,
    output_dir,
    output_file,
    parse_size,
    protocol_argument,
    protocol_of,
    real,
    run_stimulus_checks,
    verbs,
    whole,
)


def _render_overrides(args: argparse.Namespace, protocol):
    from facelab.stimuli.render.build import settings_for

    settings = settings_for(protocol)
    size = parse_size(args.size)
    if size is not None:
        from dataclasses import replace

        settings = replace(settings, width=size[0], height=size[1])
    if args.fps is not None and not 1 <= args.fps <= 240:
        raise FacelabError(f"--fps {args.fps}: expected 1..240")
    return settings


def _cmd_render(args: argparse.Namespace) -> int:
    import time

    from facelab.protocol import load_protocol
    from facelab.stimuli.render.build import build_clips, clip_counts, plan
    from facelab.stimuli.render.inputs import input_notes, load_checked_protocol
    from facelab.stimuli.render.task import render_cluster

    # refused before anything is written, as validate refuses it (the turns are checked
    # where they are read)
    protocol = load_protocol(args.protocol) if args.turn else load_checked_protocol(
        args.protocol)
    default_out = Path("results") / protocol.study.id / "clips"
    if args.turn:  # recorded live turns as the stimuli, under every condition
        from facelab.experiment.live_dialogue.turn import turns_protocol

        protocol = turns_protocol(Path(args.protocol), [Path(t) for t in args.turn])
        default_out = Path("results") / protocol.study.id / "live_clips"
    out = output_dir(args.out or default_out, option="--out")
    settings = _render_overrides(args, protocol)
    cluster = cluster_of(args)
    progress = GridProgress(quiet=args.quiet, prefix="render")
    t0 = time.perf_counter()
    n = len(plan(protocol))
    print(
        f"rendering {n} clips of {protocol.study.id!r} at {settings.width}x"
        f"{settings.height}, {args.fps or protocol.rendering.fps} fps into {out} "
        f"({render_cluster(cluster).describe()})"
    )
    for note in input_notes(protocol, base_dir=Path(args.protocol).parent):
        print(note)
    progress.start(n)
    try:
        rows = build_clips(
            protocol,
            protocol_path=Path(args.protocol),
            out=out,
            settings=settings,
            fps=args.fps,
            cluster=cluster,
            progress=progress,
            log=(lambda s: None) if args.quiet else print,
        )
    finally:
        progress.close()
    print(
        f"{clip_counts(rows)} listed in "
        f"{out / 'clips.csv'} ({time.perf_counter() - t0:.1f} s)"
    )
    run_stimulus_checks(protocol, protocol_path=Path(args.protocol), clips_dir=out,
                        accept=args.accept_check, sheets=args.contact_sheet)  # fmt: skip
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    from facelab.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    clips = Path(args.clips) if args.clips else Path("results") / protocol.study.id / "clips"
    # contact sheets already drawn (render --contact-sheet) are redrawn with the new marks
    run_stimulus_checks(protocol, protocol_path=Path(args.protocol), clips_dir=clips,
                        accept=args.accept_check,
                        sheets=any(clips.glob("contact_*.png")))  # fmt: skip
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    import numpy as np

    from facelab.protocol import load_protocol
    from facelab.stimuli.render.plots import vowel_track_figure
    from facelab.stimuli.render.prepare import find_stimulus, speech_for, tracks_for
    from facelab.stimuli.speech.track import VISEMES

    protocol = load_protocol(args.protocol)
    for option, value, ends in (("--csv", args.csv, ()), ("--plot", args.plot, figure_suffixes)):
        if value:
            output_file(value, option=option, force=args.force, suffixes=ends)
    set_id, stim = find_stimulus(protocol, args.stimulus)
    speech = speech_for(
        stim, base_dir=Path(args.protocol).parent, sample_rate=protocol.rendering.audio_sample_rate
    )
    track, isolated = tracks_for(stim, speech)
    print(f"{set_id}/{stim.id}: {speech.duration_s:.2f} s of audio, {len(track.times)} frames")
    if args.csv:
        header = "time_s," + ",".join(VISEMES)
        np.savetxt(
            args.csv,
            np.column_stack([track.times, track.weights]),
            delimiter=",",
            header=header,
            comments="",
            fmt="%.4f",
        )
        print(f"wrote {args.csv}")
    if args.plot:
        source = (
            "transcript aligned to the recording"
            if stim.transcript
            else f"analyser output (audio only, warp {track.warp:g})"
        )
        fig = vowel_track_figure(track, isolated, title=f"{set_id}/{stim.id}", source=source)
        fig.savefig(args.plot)
        print(f"wrote {args.plot}")
    return 0


def _cmd_measure_z(args: argparse.Namespace) -> int:
    import json

    from facelab.stimuli.capture.measure_z import (
        detect_onsets,
        measure_z,
        read_capture,
        read_onsets,
        write_z,
    )

    captures = [read_capture(p, fps=args.capture_fps) for p in args.captures]
    if args.onsets and args.vowels:
        raise FacelabError("give --onsets FILE or --vowels SEQUENCE, not both (the onsets are "
                           "either listed or detected in each capture's audio)")  # fmt: skip
    if args.onsets:
        onsets = read_onsets(args.onsets)
    elif args.vowels:
        onsets = []
        for cap in captures:
            audio = cap.path.with_suffix(args.audio_suffix)
            if not audio.exists():
                raise FacelabError(f"no audio {audio} for capture {cap.path} (or give --onsets)")
            onsets += detect_onsets(audio, vowels=args.vowels)
    else:
        raise FacelabError(
            "give --onsets FILE, or --vowels SEQUENCE with an audio file per capture"
        )
    out = output_file(args.out, option="--out", force=args.force)
    result = measure_z(captures, onsets, window_s=args.window)
    write_z(out, result.z)
    print(json.dumps({"z": str(out), "window_s": args.window, "spread": result.spread}, indent=2))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import json

    if getattr(args, "runs", 1) < 1:
        raise FacelabError(f"--runs {args.runs}: expected 1 or more timing runs")

    if args.action == "analyze":
        from facelab.experiment.bench import bench_analyze
        from facelab.resources import protocol_path

        given = protocol_of(args)
        proto = Path(given) if given else protocol_path("kato2021")
        print(
            json.dumps(
                bench_analyze(protocol=proto, participants=args.participants, runs=args.runs),
                indent=2,
            )
        )
        return 0
    if args.action == "online":
        from facelab.experiment.online.load import load_test, postgres_cluster

        if not protocol_of(args):
            raise FacelabError("bench online needs the PROTOCOL and --clips (rendered clips)")
        results = output_dir(args.results, option="--results")
        figures = []
        for database in ("sqlite", "postgresql") if args.db == "both" else (args.db,):
            kw = dict(protocol_path=Path(protocol_of(args)), clips=Path(args.clips),
                      participants=args.participants, results=results)  # fmt: skip
            if database == "postgresql":
                with postgres_cluster() as url:
                    figures.append(load_test(db_url=url, **kw))
            else:
                url = f"sqlite:///{(results / 'bench-online.sqlite').resolve()}"
                figures.append(load_test(db_url=url, **kw))
        print(json.dumps(figures, indent=2))
        return 0
    if args.action == "render-grid":
        from facelab.stimuli.bench import bench_render_grid

        size = parse_size(args.size) or (320, 180)
        figures = bench_render_grid(
            clips=args.clips, seconds=args.seconds, size=size, workers=args.workers,
            scheduler=args.scheduler, pin_cores=args.pin_cores,
            serial_baseline=not args.no_serial,
        )  # fmt: skip
        print(json.dumps(figures, indent=2))
        return 0
    if args.action == "visemes":
        from facelab.stimuli.bench import bench_visemes

        print(json.dumps(bench_visemes(runs=args.runs, quick=args.quick), indent=2))
        return 0
    from facelab.stimuli.bench import bench_render

    avatars = ("default", "skinned50k") if args.avatar == "all" else (args.avatar,)
    if args.size:  # side by side with 1280x720, in one run: 30 fps, the default 4x MSAA
        asked = [parse_size(text) for text in args.size]
        sizes = [(1280, 720), *(s for s in dict.fromkeys(asked) if s and s != (1280, 720))]
        rows = [
            bench_render(runs=args.runs, quick=args.quick, msaa=4, avatar=a, size=size,
                         fps_values=(30,))
            for a in avatars
            for size in sizes
        ]  # fmt: skip
    else:
        rows = [
            bench_render(runs=args.runs, quick=args.quick, msaa=m, avatar=a)
            for a in avatars
            for m in (4, 1)
        ]
    print(json.dumps(rows, indent=2))
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add(
        "render", "render every clip a protocol needs (cached) and write clips.csv", _cmd_render
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--out", metavar="DIR", help="clip folder (default results/<study>/clips)")
    p.add_argument("--turn", action="append", metavar="DIR",
                   help="a turn recorded by facelab live (repeatable): render it instead of the "
                   "protocol's stimuli, under every condition (default --out "
                   "results/<study>/live_clips)")  # fmt: skip
    p.add_argument("--contact-sheet", action="store_true", help="also write one PNG per condition")
    p.add_argument("--size", metavar="WxH", help="override the protocol's resolution")
    p.add_argument("--fps", type=whole(lo=1, hi=240), help="override the protocol's frame rate")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    check_options(p)
    cluster_options(p)

    p = add(
        "check",
        "measure every rendered clip (avatar audit, face tracker, sync, conditions, levels) "
        "and write stimulus_checks.csv",
        _cmd_check,
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--clips", metavar="DIR", help="clip folder (default results/<study>/clips)")
    check_options(p)

    p = add(
        "track", "analyse one stimulus's speech: viseme track as CSV and a vowel plot", _cmd_track
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--stimulus", required=True, metavar="SET/ID")
    p.add_argument("--plot", metavar="PNG")
    p.add_argument("--csv", metavar="FILE")
    force_option(p)

    p = add(
        "measure-z",
        "compute a Z matrix from face-capture CSV files (the paper's way)",
        _cmd_measure_z,
    )
    p.add_argument("captures", nargs="+", metavar="CAPTURE", help="Live Link Face or generic CSV")
    p.add_argument("--onsets", metavar="FILE", help="CSV: capture, vowel, onset_s[, speaker]")
    p.add_argument(
        "--vowels",
        metavar="SEQ",
        help="vowels spoken in each capture, e.g. aiueoaiueo "
        "(onsets detected from CAPTURE's audio)",
    )
    p.add_argument(
        "--audio-suffix", default=".wav", help="audio beside each capture (default .wav)"
    )
    p.add_argument(
        "--window", type=real(above=0), default=0.1, help="seconds after onset (default 0.1)"
    )
    p.add_argument(
        "--capture-fps", type=real(above=0), default=60.0,
        help="the captures' Timecode frame rate (Live Link Face; default 60)",
    )  # fmt: skip
    deprecated(p, "--fps", new="--capture-fps", dest="capture_fps", type=real(above=0))
    p.add_argument("--out", required=True, metavar="FILE", help="Z matrix CSV to write")
    force_option(p)

    p = add(
        "bench",
        "benchmarks that print JSON (visemes, render, render-grid, analyze, online)",
        _cmd_bench,
    )
    verb = verbs(p)

    def runs(v: argparse.ArgumentParser) -> None:
        v.add_argument("--runs", type=whole(lo=1), default=5, help="timing runs (median reported)")

    v = verb("visemes", "the analyser's accuracy, speed and latency per voice")
    runs(v)
    v.add_argument("--quick", action="store_true", help="fewer sentences (a smoke run)")
    v = verb("render", "render real-time factor, stage timing, A/V offset")
    runs(v)
    v.add_argument("--quick", action="store_true", help="a shorter clip (a smoke run)")
    v.add_argument(
        "--avatar", choices=["all", "default", "skinned50k"], default="all",
        help="the default head, a skinned ~50k-vertex sample, or both (default)",
    )  # fmt: skip
    v.add_argument(
        "--size", action="append", metavar="WxH",
        help="also time this resolution (repeatable), beside 1280x720 in the same run, at "
        "30 fps and 4x MSAA (e.g. --size 1920x1080)",
    )  # fmt: skip
    v = verb("render-grid", "a fixed grid of short clips, serially and on Dask workers")
    v.add_argument("--clips", type=whole(lo=1), default=24, help="clips in the grid (24)")
    v.add_argument("--seconds", type=real(above=0), default=4.0, help="seconds per clip (4)")
    v.add_argument("--size", metavar="WxH", help="default 320x180")
    cluster_options(v, what="grid")
    v.add_argument("--pin-cores", action="store_true",
                   help="pin the serial run to one CPU and local worker i to CPU i (each "
                   "worker stands for a single-core machine)")  # fmt: skip
    v.add_argument("--no-serial", action="store_true",
                   help="with --workers/--scheduler: skip the serial baseline run")  # fmt: skip
    v = verb("analyze", "facelab analyze on N simulated participants")
    protocol_argument(v, optional=True)
    runs(v)
    v.add_argument("--participants", type=whole(lo=1), default=1000,
                   help="simulated participants (default 1000)")  # fmt: skip
    v = verb("online", "load test of facelab serve")
    protocol_argument(v, optional=True)
    runs(v)
    v.add_argument("--clips", required=True, metavar="DIR", help="the protocol's rendered clips")
    v.add_argument("--participants", type=whole(lo=1), default=200,
                   help="concurrent clients (default 200)")  # fmt: skip
    v.add_argument("--db", choices=["sqlite", "postgresql", "both"], default="both",
                   help="database(s) to load (PostgreSQL: a temporary server)")  # fmt: skip
    v.add_argument("--results", default="results/bench", metavar="DIR",
                   help="where the SQLite database goes")  # fmt: skip
