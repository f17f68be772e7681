"""Online commands: ``serve`` (the study in participants' browsers) and ``export`` (the
database as the lab runner's session files)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    add_conversation_options,
    conversation_talker,
    output_dir,
    parse_size,
    seed,
    whole,
)


def _cmd_serve(args: argparse.Namespace) -> int:
    from facelab.experiment.online.serve import BackgroundServer, prepare_server
    from facelab.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    results = output_dir(args.results, option="--results")
    if not 0 <= args.port <= 65535:
        raise FacelabError(f"--port {args.port}: expected 1..65535 (0: any free port)")
    if args.simulate_participants is not None and args.simulate_participants < 1:
        raise FacelabError("--simulate-participants: expected a number >= 1")
    window = None
    if args.simulate_window is not None:
        if not args.simulate_participants:
            raise FacelabError("--simulate-window: only with --simulate-participants N")
        window = parse_size(args.simulate_window, option="--simulate-window")
    asked = {"--simulate-headset-off": args.simulate_headset_off is not None,
             "--simulate-vr-input": args.simulate_vr_input is not None}  # fmt: skip
    headset = [flag for flag, given in asked.items() if given]
    if headset and not args.simulate_participants:
        raise FacelabError(f"{headset[0]}: only with --simulate-participants N")
    if headset and protocol.presentation.display != "webxr":
        raise FacelabError(
            f"{headset[0]}: the simulated participants wear a headset only when the protocol's "
            f"presentation.display is webxr ({args.protocol} has "
            f"{protocol.presentation.display})"
        )
    consent = None
    if args.consent:
        try:
            consent = Path(args.consent).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise FacelabError(
                f"--consent {args.consent}: cannot read it as UTF-8 text ({exc})"
            ) from None
    clips = Path(args.clips) if args.clips else results / protocol.study.id / "clips"
    routes = ()
    talker = conversation_talker(args, protocol)
    if talker is not None:  # the talker's voice drives the avatar
        from facelab.experiment.live_dialogue.conversation import conversation_routes

        routes = (conversation_routes(
            protocol, protocol_path=Path(args.protocol),
            folder=results / protocol.study.id / "conversations", talker=talker,
            playout_ms=args.conversation_playout_ms,
        ),)  # fmt: skip
    server, made = prepare_server(
        protocol,
        protocol_path=Path(args.protocol),
        clips_dir=clips,
        db_url=args.db,
        results=results,
        completion_url=args.completion_url,
        completion_code=args.completion_code,
        consent=consent,
        admin_secret=os.environ.get("FACELAB_ADMIN_SECRET"),
        routes=routes,
    )
    if args.simulate_participants:
        from facelab.experiment.online.browser import WINDOW, run_simulated

        with BackgroundServer(server, host=args.host, port=args.port) as bg:
            print(f"serving {protocol.study.id!r} at {bg.url} for simulated participants")

            def progress(k: int, outcome: str) -> None:
                print(f"  simulated participant {k}: {outcome}", flush=True)

            outcomes = run_simulated(
                server,
                bg.url,
                args.simulate_participants,
                seed=args.sim_seed,
                parallel=args.parallel,
                screenshots=Path(args.screenshots) if args.screenshots else None,
                progress=progress,
                headset_off_at=args.simulate_headset_off,
                vr_input=args.simulate_vr_input or "controller",
                window=window or WINDOW,
            )
        done = sum(o == "complete" for o in outcomes.values())
        print(f"{done} of {len(outcomes)} simulated participants complete")
        return 0 if done == len(outcomes) else 1

    import socket

    import uvicorn

    from facelab.experiment.online.app import create_app
    from facelab.experiment.online.serve import proxy_options

    with socket.socket() as probe:  # as uvicorn binds: TIME_WAIT after a restart is fine
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((args.host, args.port))
        except OSError as exc:
            raise FacelabError(
                f"--host {args.host} --port {args.port}: cannot listen ({exc})"
            ) from None

    base = f"http://{args.host}:{args.port}"
    print(f"serving study {protocol.study.id!r} at {base} (database {server.engine.url!r})")
    print(
        f"  participants' link:  {base}/join   (Prolific: {base}/join?PROLIFIC_PID="
        "{{%PROLIFIC_PID%}})"
    )
    print(f"  experimenter page:   {base}/admin")
    if routes:
        print(f"  talker page:         {base}/talk   (the live conversation's talker)")
    if args.forwarded_allow_ips:
        print(f"  client addresses:    from X-Forwarded-For set by {args.forwarded_allow_ips}")
    else:
        print(
            "  client addresses:    the connection's (behind a reverse proxy, give "
            "--forwarded-allow-ips PROXY so the join limit counts participants, not the proxy)"
        )
    if made:
        print(
            f"  experimenter secret: {made}   (new for this run; set FACELAB_ADMIN_SECRET "
            "to keep one)"
        )
    sys.stdout.flush()
    uvicorn.run(
        create_app(server),
        host=args.host,
        port=args.port,
        log_level="warning",
        **proxy_options(args.forwarded_allow_ips),
    )
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from facelab.experiment.online.db import REVISIONS, facelab_revision, open_engine
    from facelab.experiment.online.export import export_sessions

    results = output_dir(args.results, option="--results")
    if args.db.startswith("sqlite:///") and not Path(args.db[len("sqlite:///") :]).is_file():
        raise FacelabError(f"--db {args.db}: no such database file (nothing was exported)")
    protocol = digest = None
    if args.protocol:
        from facelab.protocol import load_protocol, protocol_hash

        protocol = load_protocol(args.protocol)
        digest = protocol_hash(args.protocol)
    revision = facelab_revision(args.db)  # read without changing the database
    if revision is None:
        raise FacelabError(
            f"--db {args.db}: not a facelab online database (it holds no facelab tables); "
            "nothing was exported and the database was not changed"
        )
    if revision not in REVISIONS:
        raise FacelabError(
            f"--db {args.db}: made by a newer facelab (schema {revision}; this one knows up "
            f"to {REVISIONS[-1]}); export it with that version"
        )
    engine = open_engine(args.db)  # an older facelab's database is brought up to date
    notes: list[str] = []
    quarantine: list[str] = []
    paths = export_sessions(
        engine,
        results=results,
        study=args.study or (protocol.study.id if protocol else None),
        protocol=protocol,
        protocol_sha256=digest,
        notes=notes,
        quarantine=quarantine,
    )
    print(f"exported {len(paths)} online sessions into {results}")
    for p in paths:
        print(f"  {p}")
    for note in notes:
        print(f"  note: {note}")
    for line in quarantine:
        print(f"  quarantined: {line}", file=sys.stderr)
    if quarantine:
        print(f"facelab export: {len(quarantine)} session(s) quarantined (above); every other "
              "session was exported (exit 3)", file=sys.stderr)  # fmt: skip
        return 3
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add("serve", "serve the study to participants' browsers (online sessions)", _cmd_serve)
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument(
        "--db",
        metavar="URL",
        help="database URL: sqlite:///PATH (default results/<study>/online.sqlite) or "
        "postgresql+psycopg://USER@HOST/DB",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=whole(lo=0, hi=65535), default=8000, help="port (default 8000)")
    p.add_argument(
        "--forwarded-allow-ips", metavar="IPS",
        help="the reverse proxies (comma-separated addresses) whose X-Forwarded-For is trusted "
        "for the client's address; default none: the header is ignored",
    )  # fmt: skip
    p.add_argument("--clips", metavar="DIR", help="rendered clips (default results/<study>/clips)")
    p.add_argument("--results", default="results", metavar="DIR", help="results root")
    p.add_argument("--consent", metavar="FILE", help="text shown first, with an 'I agree' button")
    p.add_argument(
        "--completion-url",
        metavar="URL",
        help="where the end screen sends a participant whose every response is stored "
        "(e.g. https://app.prolific.com/submissions/complete?cc=CODE)",
    )
    p.add_argument("--completion-code", metavar="CODE", help="a code shown on the end screen")
    p.add_argument(
        "--simulate-participants",
        type=whole(lo=1, hi=1000),
        metavar="N",
        help="drive N simulated participants through the real pages in headless Chromium, "
        "then exit (the same N ids and tokens on every start: a second start resumes them)",
    )
    p.add_argument("--sim-seed", type=seed, default=1, metavar="S", help="seed of their answers")
    p.add_argument("--parallel", type=whole(lo=1), default=2, metavar="K", help="browsers at once")
    p.add_argument("--screenshots", metavar="DIR", help="PNGs of the first participant's screens")
    p.add_argument(
        "--simulate-window",
        metavar="WxH",
        help="the simulated participants' browser window (default 1280x800); an emulated "
        "headset draws both eyes into it, so a smaller one (e.g. 640x400) runs a VR session "
        "faster on a machine without a GPU, with smaller screenshots",
    )
    add_conversation_options(p, who="the participant")
    p.add_argument(
        "--simulate-headset-off",
        type=whole(lo=1),
        metavar="TRIAL",
        help="display webxr: the first simulated participant takes the headset off for a "
        "second during the clip of this trial (the clip stops, and plays again once seen)",
    )
    p.add_argument(
        "--simulate-vr-input",
        choices=("controller", "gaze"),  # browser.VR_INPUTS (not imported for --help)
        help="display webxr: the simulated participants' emulated headset has two controllers "
        "(default) or none (gaze-only: they look at what they select and press its button)",
    )

    p = add(
        "export",
        "write the online database's sessions as the lab runner's files (for facelab analyze)",
        _cmd_export,
    )
    p.add_argument("--db", required=True, metavar="URL", help="the database facelab serve used")
    p.add_argument("--results", required=True, metavar="DIR", help="results root to write into")
    p.add_argument("--study", metavar="ID", help="only this study")
    p.add_argument(
        "--protocol",
        metavar="P",
        help="the protocol the sessions ran: also writes each staircase session's "
        "_staircase.jsonl (the database does not hold the protocol); implies --study",
    )
