"""Session commands: ``run`` (a participant in a window) and ``simulate``."""

from __future__ import annotations

import argparse
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    add_conversation_options,
    conversation_talker,
    deprecated,
    output_dir,
    parse_effects,
    parse_session,
    parse_size,
    seed,
    whole,
)


def _cmd_run(args: argparse.Namespace) -> int:
    from facelab.design import validate_participant_id
    from facelab.experiment.runner import RunOptions, run_session
    from facelab.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    validate_participant_id(args.participant)
    output_dir(args.results, option="--results")
    size = parse_size(args.size, largest=None) or (1280, 800)  # a window
    talker = conversation_talker(args, protocol)
    conversation = None
    if talker is not None:  # the partner drawn live in this window, heard on its speakers
        from facelab.experiment.live_dialogue.app import LIVE_RATE
        from facelab.experiment.live_dialogue.lab_conversation import LabConversation
        from facelab.experiment.live_dialogue.window_view import SoundOut

        SoundOut.check(sample_rate=LIVE_RATE)
        conversation = LabConversation(
            protocol=protocol, protocol_path=Path(args.protocol), results=Path(args.results),
            talker=talker, playout_ms=args.conversation_playout_ms,
            host=args.conversation_host, port=args.conversation_port,
        )  # fmt: skip
        conversation.check(conditions=[protocol.presentation.conversation.condition])
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
        accept_changed_clips=args.accept_changed_clips,
        warn_dropped_frames=args.warn_dropped_frames,
        conversation=conversation,
    )
    summary = run_session(protocol, protocol_path=Path(args.protocol), options=options)
    state = "complete" if summary["complete"] else "incomplete"
    drops = summary.get("dropped")
    dropped = (
        f"; clips dropped {drops['frames_dropped']} frames in {drops['trials_with_drops']} of "
        f"{drops['trials']} trials (at most {drops['max_dropped']})"
        if drops
        else ""
    )
    print(
        f"session {state}: {summary['ratings']} ratings in {summary['log']} "
        f"({summary['trials_run']} trials this run{dropped})"
    )
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from facelab.experiment.simulate import simulate_study
    from facelab.protocol import load_protocol

    if args.sim_seed is None:
        raise FacelabError("facelab simulate needs --sim-seed S (the seed of the answers)")
    protocol = load_protocol(args.protocol)
    results = output_dir(args.results, option="--results")
    paths = simulate_study(
        protocol,
        protocol_path=Path(args.protocol),
        results=results,
        participants=args.participants,
        seed=args.sim_seed,
        effects=parse_effects(args.effect),
    )
    print(
        f"simulated {len(paths)} participants of study {protocol.study.id!r} "
        f"(seed {args.sim_seed}) into {results / protocol.study.id}"
    )
    for p in paths:
        print(f"  {p.tsv}")
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add("run", "run a participant session in a PsychoPy window", _cmd_run)
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participant", required=True, metavar="ID")
    p.add_argument("--session", type=parse_session, default=1, metavar="N", help="1..9999")
    p.add_argument("--resume", action="store_true", help="continue an interrupted session")
    p.add_argument(
        "--accept-changed-clips",
        action="store_true",
        help="with --resume: continue although clips differ from those the session started "
        "with (recorded in the session file)",
    )
    p.add_argument("--windowed", action="store_true", help="a window instead of full screen")
    p.add_argument(
        "--warn-dropped-frames", type=whole(lo=0), default=3, metavar="N",
        help="name a clip that drops more than N frames at once (default 3); each block and "
        "the session end with a count",
    )  # fmt: skip
    p.add_argument("--size", metavar="WxH", help="window size with --windowed (default 1280x800)")
    p.add_argument(
        "--simulate",
        action="store_true",
        help="a scripted participant drives the real window (xdotool clicks; for tests)",
    )
    p.add_argument(
        "--sim-seed", type=seed, default=1, metavar="S", help="seed of the scripted ratings"
    )
    p.add_argument("--clips", metavar="DIR", help="rendered clips (default results/<study>/clips)")
    p.add_argument("--results", default="results", metavar="DIR", help="results root")
    p.add_argument(
        "--screenshots", metavar="DIR", help="save PNGs of a clip frame and a VAS screen"
    )
    add_conversation_options(p, who="the participant")
    p.add_argument("--conversation-host", default="127.0.0.1", metavar="HOST",
                   help="presentation.conversation: the talker's page is served here (default "
                   "127.0.0.1; the lab network's address for a talker on another machine)")
    p.add_argument("--conversation-port", type=whole(lo=1, hi=65535), default=8010,
                   metavar="PORT", help="... and on this port (default 8010)")

    p = add(
        "simulate",
        "write complete sessions of simulated participants (through the same session log as "
        "real ones)",
        _cmd_simulate,
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participants", type=whole(lo=1, hi=5000), default=8, metavar="N")
    p.add_argument("--sim-seed", type=seed, metavar="S", help="seed of the answers (required)")
    deprecated(p, "--seed", new="--sim-seed", dest="sim_seed", type=seed)
    p.add_argument(
        "--effect",
        action="append",
        metavar="COND=POINTS",
        help="condition effect in VAS points, replacing the protocol's (repeatable)",
    )
    p.add_argument("--results", default="results", metavar="DIR", help="results root")
