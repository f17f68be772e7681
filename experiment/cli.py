"""The ``facelab`` command line: one subcommand per stage.

Exit status: 0 success; 2 a user mistake (bad protocol, option, file), reported as one clear
message without a traceback; 4 a session stopped by the experimenter (ratings kept);
130 interrupted.
This is the only module that reads the process environment and turns paths from the user
into objects for the pure modules.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from experiment.errors import FacelabError

__all__ = ["main"]

Handler = Callable[[argparse.Namespace], int]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("facelab")
    except PackageNotFoundError:  # running from a source tree without installing
        return "0+unknown"


# --------------------------------------------------------------------------- built stages


def _cmd_validate(args: argparse.Namespace) -> int:
    from experiment.design import build_trials
    from experiment.protocol import load_protocol

    for path in args.protocols:
        protocol = load_protocol(path)
        n_trials = len(build_trials(protocol, participant="P1"))
        print(
            f"ok: {path}: study {protocol.study.id!r}, {len(protocol.conditions)} conditions, "
            f"{sum(len(s.stimuli) for s in protocol.stimulus_sets)} stimuli in "
            f"{len(protocol.stimulus_sets)} sets, {len(protocol.blocks)} blocks, "
            f"{n_trials} trials x {len(protocol.items)} items per participant"
        )
    return 0


def _cmd_design(args: argparse.Namespace) -> int:
    from experiment.design import build_trials, trials_frame
    from experiment.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    frame = trials_frame(build_trials(protocol, participant=args.participant, seed=args.seed))
    if args.out:
        out = Path(args.out)
        if out.exists() and not args.force:
            raise FacelabError(f"{out} exists; choose another file or pass --force to replace it")
        frame.to_csv(out, index=False)
        print(f"wrote {len(frame)} trials to {out}", file=sys.stderr)
    else:
        frame.to_csv(sys.stdout, index=False, lineterminator="\n")
    return 0


def _cmd_schema(args: argparse.Namespace) -> int:
    from experiment.protocol import schema_json_text

    text = schema_json_text()
    if args.out:
        Path(args.out).write_text(text, encoding="utf-8")
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def _parse_effects(pairs: list[str] | None) -> dict[str, float] | None:
    if not pairs:
        return None
    effects: dict[str, float] = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            effects[name] = float(value)
        except ValueError:
            raise FacelabError(
                f"--effect {pair!r}: expected CONDITION=POINTS, e.g. standard=15"
            ) from None
    return effects


def _cmd_simulate(args: argparse.Namespace) -> int:
    from experiment.protocol import load_protocol
    from experiment.simulate import simulate_study

    protocol = load_protocol(args.protocol)
    results = Path(args.results)
    paths = simulate_study(
        protocol,
        protocol_path=Path(args.protocol),
        results=results,
        participants=args.participants,
        seed=args.seed,
        effects=_parse_effects(args.effect),
    )
    print(
        f"simulated {len(paths)} participants of study {protocol.study.id!r} (seed {args.seed}) "
        f"into {results / protocol.study.id}"
    )
    for p in paths:
        print(f"  {p.tsv}")
    return 0


def _cmd_analyze(args: argparse.Namespace) -> int:
    from analysis.load import load_results
    from analysis.report import write_report
    from analysis.study import analyze_study
    from experiment.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    results_dir = Path(args.results)
    data = load_results(results_dir, study=protocol.study.id)
    if args.exclude:
        unknown = sorted(set(args.exclude) - set(data["participant"]))
        if unknown:
            raise FacelabError(
                f"--exclude: no such participant(s) in the logs: {', '.join(unknown)}"
            )
        data = data[~data["participant"].isin(args.exclude)].reset_index(drop=True)
    results = analyze_study(data, protocol, method=args.method)
    if args.out:
        out = Path(args.out)
    elif results_dir.name == protocol.study.id:
        out = results_dir / "analysis"
    else:
        out = results_dir / protocol.study.id / "analysis"
    files = write_report(
        results=results, data=data, protocol=protocol, out=out, protocol_path=Path(args.protocol)
    )
    kind = "SIMULATED " if data["simulated"].all() else ""
    print(
        f"analysed {len(data)} {kind}ratings from {data['participant'].nunique()} participants "
        f"(primary procedure: {args.method})"
    )
    for row in results.layout.itertuples():
        print(
            f"  {row.item:>12} / {row.stimulus_set:<10} {row.procedure:>5}: "
            f"F({row.df1:g},{row.df2:g}) = {row.f:7.3f}, p = {row.anova_p:.4f}; "
            f"pairs p<.05: {row.pairs_p_lt_05}"
        )
    print(f"report: {files.html}\ntables and figures: {files.folder}")
    return 0


def _cmd_power(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from analysis import power

    rows: list[dict[str, object]] = []
    assumptions = ""
    if args.pilot:
        from analysis.load import load_results
        from experiment.protocol import load_protocol

        if not args.protocol:
            raise FacelabError("--pilot needs --protocol (for the study id and conditions)")
        protocol = load_protocol(args.protocol)
        data = load_results(args.pilot, study=protocol.study.id)
        for item in protocol.items:
            for sset in protocol.stimulus_sets:
                sub = data[(data["item"] == item.id) & (data["stimulus_set"] == sset.id)]
                if not sub.empty:
                    rows.append({"label": f"{item.id}/{sset.id}", **power.f2_from_pilot(sub)})
        assumptions = "effect sizes from pilot data (participant means, bias-corrected)"
    elif args.reported_p is not None:
        for p in args.reported_p:
            est = power.f2_from_reported_p(
                p=p,
                participants=args.participants,
                conditions=args.conditions,
                reps=args.reps,
                icc=args.icc,
                interaction_share=args.interaction_share,
            )
            rows.append({"label": f"reported p={p:g}", "k": args.conditions, **est})
        assumptions = (
            "from the paper procedure's p (pooled one-way ANOVA, "
            f"{args.participants} participants x "
            f"{args.conditions} conditions x {args.reps} ratings); assumed variance split: "
            f"participant {args.icc:g}, participant x condition {args.interaction_share:g}, "
            f"rating noise {1 - args.icc - args.interaction_share:g}"
        )
    else:
        raise FacelabError("give --reported-p P [P ...] (with the design) or --pilot RESULTS")
    rng = np.random.default_rng(args.seed)
    for row in rows:
        k = int(row.get("k", args.conditions))
        n_needed = power.participants_needed(
            k=k, f2=float(row["f2_rm"]), power=args.power, alpha=args.alpha
        )
        row["k"] = k
        row["power_at_n"] = power.rm_power(
            n=args.participants, k=k, f2=float(row["f2_rm"]), alpha=args.alpha
        )
        row["n_needed"] = n_needed
        row["simulated_power_at_needed"] = (
            power.simulate_power(
                n=n_needed, k=k, f2=float(row["f2_rm"]), alpha=args.alpha, sims=args.sims, rng=rng
            )
            if n_needed
            else None
        )
    if args.json:
        print(
            json.dumps(
                {
                    "assumptions": assumptions,
                    "alpha": args.alpha,
                    "target_power": args.power,
                    "n": args.participants,
                    "rows": rows,
                },
                indent=2,
            )
        )
        return 0
    print(
        f"power of the repeated-measures ANOVA on participant means (alpha {args.alpha:g}); "
        f"{assumptions}"
    )
    for row in rows:
        extra = (
            f", pilot F {row['f_pilot']:.2f}"
            if "f_pilot" in row
            else (f", implied F {row['f']:.2f}, eta_p^2 {row['eta_p_sq']:.3f}")
        )
        need = row["n_needed"] if row["n_needed"] else "> 10000"
        sim = row["simulated_power_at_needed"]
        sim_text = f" (simulated: {sim:.3f} over {args.sims} runs)" if sim is not None else ""
        print(
            f"  {row['label']}: f2_rm {float(row['f2_rm']):.3f}{extra}; power with "
            f"n={args.participants}: {float(row['power_at_n']):.3f}; n for "
            f"{args.power:g} power: {need}{sim_text}"
        )
    return 0


def _cmd_track(args: argparse.Namespace) -> int:
    import numpy as np

    from experiment.protocol import load_protocol
    from stimuli.plots import vowel_track_figure
    from stimuli.prepare import find_stimulus, speech_for, tracks_for
    from stimuli.visemes import VISEMES

    protocol = load_protocol(args.protocol)
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
        fig = vowel_track_figure(track, isolated, title=f"{set_id}/{stim.id}")
        fig.savefig(args.plot)
        print(f"wrote {args.plot}")
    return 0


def _cmd_measure_z(args: argparse.Namespace) -> int:
    import json

    from stimuli.measure_z import detect_onsets, measure_z, read_capture, read_onsets, write_z

    captures = [read_capture(p, fps=args.fps) for p in args.captures]
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
    out = Path(args.out)
    if out.exists() and not args.force:
        raise FacelabError(f"{out} exists; choose another file or pass --force")
    result = measure_z(captures, onsets, window_s=args.window)
    write_z(out, result.z)
    print(json.dumps({"z": str(out), "window_s": args.window, "spread": result.spread}, indent=2))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import json

    if args.what == "visemes":
        from stimuli.bench import bench_visemes

        print(json.dumps(bench_visemes(runs=args.runs, quick=args.quick), indent=2))
        return 0
    from stimuli.bench import bench_render

    print(
        json.dumps(
            [bench_render(runs=args.runs, quick=args.quick, msaa=m) for m in (4, 1)], indent=2
        )
    )
    return 0


def _parse_size(text: str | None) -> tuple[int, int] | None:
    """``WIDTHxHEIGHT`` -> (width, height); even numbers >= 64 (H.264 needs even sizes)."""
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise FacelabError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x360") from None
    if w % 2 or h % 2 or w < 64 or h < 64:
        raise FacelabError(f"--size {text!r}: width and height must be even and >= 64")
    return w, h


def _render_overrides(args: argparse.Namespace, protocol):
    from stimuli.build import settings_for

    settings = settings_for(protocol)
    size = _parse_size(args.size)
    if size is not None:
        from dataclasses import replace

        settings = replace(settings, width=size[0], height=size[1])
    if args.fps is not None and not 1 <= args.fps <= 240:
        raise FacelabError(f"--fps {args.fps}: expected 1..240")
    return settings


def _cmd_render(args: argparse.Namespace) -> int:
    import time

    from tqdm import tqdm

    from experiment.protocol import load_protocol
    from stimuli.build import build_clips, contact_sheets, plan

    protocol = load_protocol(args.protocol)
    out = Path(args.out) if args.out else Path("results") / protocol.study.id / "clips"
    settings = _render_overrides(args, protocol)
    bars: list[tqdm] = []

    def progress(name: str, total: int):
        bar = tqdm(total=total, desc=name[:40], unit="frame", leave=False, disable=args.quiet)
        bars.append(bar)
        return lambda: bar.update(1)

    t0 = time.perf_counter()
    print(
        f"rendering {len(plan(protocol))} clips of {protocol.study.id!r} at {settings.width}x"
        f"{settings.height}, {args.fps or protocol.rendering.fps} fps into {out}"
    )
    rows = build_clips(
        protocol,
        protocol_path=Path(args.protocol),
        out=out,
        settings=settings,
        fps=args.fps,
        progress=progress,
        log=(lambda s: None) if args.quiet else print,
    )
    for bar in bars:
        bar.close()
    fresh = sum(r["status"] == "rendered" for r in rows)
    print(
        f"{len(rows)} clips ({fresh} rendered, {len(rows) - fresh} unchanged and reused) listed in "
        f"{out / 'clips.csv'} ({time.perf_counter() - t0:.1f} s)"
    )
    if args.contact_sheet:
        for path in contact_sheets(
            protocol, protocol_path=Path(args.protocol), out=out, settings=settings
        ):
            print(f"contact sheet: {path}")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from experiment.design import validate_participant_id
    from experiment.protocol import load_protocol
    from experiment.runner import RunOptions, run_session

    protocol = load_protocol(args.protocol)
    validate_participant_id(args.participant)
    if args.session < 1:
        raise FacelabError(f"--session {args.session}: sessions are numbered from 1")
    size = _parse_size(args.size) or (1280, 800)
    options = RunOptions(
        participant=args.participant,
        session=args.session,
        resume=args.resume,
        windowed=args.windowed,
        simulate=args.simulate,
        sim_seed=args.sim_seed,
        clips=Path(args.clips) if args.clips else None,
        results=Path(args.results),
        screenshots=Path(args.screenshots) if args.screenshots else None,
        size=size,
    )
    summary = run_session(protocol, protocol_path=Path(args.protocol), options=options)
    state = "complete" if summary["complete"] else "incomplete"
    print(
        f"session {state}: {summary['ratings']} ratings in {summary['log']} "
        f"({summary['trials_run']} trials this run)"
    )
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from experiment.demo import DEFAULT_PROTOCOL, run_demo

    size = _parse_size(args.size)
    bars: list[tqdm] = []

    def progress(name: str, total: int):
        bar = tqdm(
            total=total, desc=f"render {name[:34]}", unit="frame", leave=False, disable=args.quiet
        )
        bars.append(bar)
        return lambda: bar.update(1)

    try:
        run_demo(
            out=Path(args.out),
            protocol_path=Path(args.protocol) if args.protocol else DEFAULT_PROTOCOL,
            participants=args.participants,
            seed=args.seed,
            size=size,
            fps=args.fps,
            progress=progress,
        )
    finally:
        for bar in bars:
            bar.close()
    return 0


# --------------------------------------------------------------------------- parser


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="facelab",
        description="Perception experiments on talking 3D avatar heads: one protocol file -> "
        "rendered clips -> participant sessions with VAS ratings -> analysis and report.",
    )
    parser.add_argument("--version", action="version", version=f"facelab {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name: str, help_text: str, handler: Handler) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(handler=handler)
        return p

    p = add("validate", "check protocol files; print a summary of each", _cmd_validate)
    p.add_argument("protocols", nargs="+", metavar="PROTOCOL", help="protocol YAML file(s)")

    p = add("design", "print a participant's ordered trial list as CSV", _cmd_design)
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participant", required=True, metavar="ID", help="participant id, e.g. P01")
    p.add_argument("--seed", type=int, metavar="N", help="study seed instead of the protocol's")
    p.add_argument("--out", metavar="FILE", help="write the CSV to FILE instead of stdout")
    p.add_argument("--force", action="store_true", help="replace FILE if it exists")

    p = add("schema", "print the protocol JSON Schema (as in protocols/schema/)", _cmd_schema)
    p.add_argument("--out", metavar="FILE", help="write to FILE instead of stdout")

    p = add(
        "render", "render every clip a protocol needs (cached) and write clips.csv", _cmd_render
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--out", metavar="DIR", help="clip folder (default results/<study>/clips)")
    p.add_argument("--contact-sheet", action="store_true", help="also write one PNG per condition")
    p.add_argument("--size", metavar="WxH", help="override the protocol's resolution")
    p.add_argument("--fps", type=int, help="override the protocol's frame rate")
    p.add_argument("--quiet", action="store_true", help="no progress bars")

    p = add("run", "run a participant session in a PsychoPy window", _cmd_run)
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participant", required=True, metavar="ID")
    p.add_argument("--session", type=int, default=1, metavar="N")
    p.add_argument("--resume", action="store_true", help="continue an interrupted session")
    p.add_argument("--windowed", action="store_true", help="a window instead of full screen")
    p.add_argument("--size", metavar="WxH", help="window size with --windowed (default 1280x800)")
    p.add_argument(
        "--simulate",
        action="store_true",
        help="a scripted participant drives the real window (xdotool clicks; for tests)",
    )
    p.add_argument(
        "--sim-seed", type=int, default=1, metavar="S", help="seed of the scripted ratings"
    )
    p.add_argument("--clips", metavar="DIR", help="rendered clips (default results/<study>/clips)")
    p.add_argument("--results", default="results", metavar="DIR", help="results root")
    p.add_argument(
        "--screenshots", metavar="DIR", help="save PNGs of a clip frame and a VAS screen"
    )

    p = add(
        "simulate",
        "write complete sessions of simulated participants (through the same session log as "
        "real ones)",
        _cmd_simulate,
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participants", type=int, default=8, metavar="N")
    p.add_argument("--seed", type=int, required=True, metavar="S", help="seed of the ratings")
    p.add_argument(
        "--effect",
        action="append",
        metavar="COND=POINTS",
        help="condition effect in VAS points, replacing the protocol's (repeatable)",
    )
    p.add_argument("--results", default="results", metavar="DIR", help="results root")

    p = add("analyze", "analyse session logs into tables, figures and a report", _cmd_analyze)
    p.add_argument("results", metavar="RESULTS", help="results root or the study's folder")
    p.add_argument("--protocol", required=True, metavar="PROTOCOL")
    p.add_argument(
        "--method",
        choices=["rm", "paper"],
        default="rm",
        help="primary procedure: rm (sound, default) or paper (pooled ANOVA + Tukey)",
    )
    p.add_argument("--exclude", action="append", metavar="ID", help="leave out a participant")
    p.add_argument(
        "--out", metavar="DIR", help="output folder (default <results>/<study>/analysis)"
    )

    p = add(
        "power",
        "implied effect size and participants needed for a chosen power (RM analysis)",
        _cmd_power,
    )
    p.add_argument(
        "--reported-p",
        type=float,
        nargs="+",
        metavar="P",
        help="p-value(s) reported for the paper's pooled one-way ANOVA",
    )
    p.add_argument("--pilot", metavar="RESULTS", help="pilot session logs instead of a p-value")
    p.add_argument("--protocol", metavar="PROTOCOL", help="the pilot's protocol")
    p.add_argument(
        "--participants",
        type=int,
        default=8,
        metavar="N",
        help="participants of the reported study (and n for 'power at n')",
    )
    p.add_argument("--conditions", type=int, default=3, metavar="K")
    p.add_argument(
        "--reps", type=int, default=2, metavar="R", help="ratings per participant x condition"
    )
    p.add_argument("--icc", type=float, default=0.3, help="assumed participant share of variance")
    p.add_argument(
        "--interaction-share",
        type=float,
        default=0.1,
        help="assumed participant x condition share of variance",
    )
    p.add_argument("--power", type=float, default=0.8, help="target power")
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--sims", type=int, default=4000, help="Monte Carlo runs for the check")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", action="store_true", help="print JSON")

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
    p.add_argument("--window", type=float, default=0.1, help="seconds after onset (default 0.1)")
    p.add_argument("--fps", type=float, default=60.0, help="Live Link Face timecode frame rate")
    p.add_argument("--out", required=True, metavar="FILE", help="Z matrix CSV to write")
    p.add_argument("--force", action="store_true")

    p = add(
        "track", "analyse one stimulus's speech: viseme track as CSV and a vowel plot", _cmd_track
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--stimulus", required=True, metavar="SET/ID")
    p.add_argument("--plot", metavar="PNG")
    p.add_argument("--csv", metavar="FILE")

    p = add(
        "demo",
        "the whole study on the embedded defaults: render, simulate, analyse, report",
        _cmd_demo,
    )
    p.add_argument(
        "--out", default="results/demo", metavar="DIR", help="output folder (default results/demo)"
    )
    p.add_argument(
        "--protocol", metavar="PROTOCOL", help="another protocol instead of kato2021.yaml"
    )
    p.add_argument("--participants", type=int, default=8, metavar="N")
    p.add_argument(
        "--seed", type=int, default=2021, metavar="S", help="seed of the simulated ratings"
    )
    p.add_argument(
        "--size", metavar="WxH", help="override the resolution (e.g. 320x180 for a quick run)"
    )
    p.add_argument("--fps", type=int, help="override the frame rate")
    p.add_argument("--quiet", action="store_true", help="no progress bars")

    p = add("bench", "benchmarks that print JSON (visemes, render)", _cmd_bench)
    p.add_argument("what", choices=["visemes", "render"])
    p.add_argument("--runs", type=int, default=5, help="timing runs (median reported)")
    p.add_argument("--quick", action="store_true", help="fewer sentences (a smoke run)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args))
    except FacelabError as exc:
        print(f"facelab {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"facelab {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `facelab design ... | head`
        sys.stderr.close()
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
