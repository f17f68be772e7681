"""Live dialogue: ``facelab live`` (a talker's voice drives the avatar as it streams)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import AddCommand, output_file, real, whole


def _config(args: argparse.Namespace):
    from facelab.experiment.live_dialogue.app import LiveConfig
    from facelab.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    ids = [c.id for c in protocol.conditions]
    if args.condition not in ids:
        raise FacelabError(f"--condition {args.condition}: the protocol's conditions are "
                           f"{', '.join(ids)}")  # fmt: skip
    if args.display == "window":
        raise FacelabError(
            "--display window: the lab window cannot show a live avatar yet (it plays rendered "
            "clips); use --display live3d (a browser on this or another machine) or webxr"
        )
    talker: str | Path = "mic"
    if args.input not in (None, "mic"):
        talker = Path(args.input)
        if not talker.is_file():
            raise FacelabError(f"--input {talker}: no such audio file (or give 'mic')")
    session = Path(args.session or Path("results") / protocol.study.id / "live" / args.condition)
    if session.exists() and not session.is_dir():
        raise FacelabError(f"--session {session}: is a file, not a folder")
    return LiveConfig(
        protocol=protocol, protocol_path=Path(args.protocol), condition=args.condition,
        session=session, talker=talker, display=args.display, playout_ms=args.playout_ms,
    )  # fmt: skip


def _cmd_live(args: argparse.Namespace) -> int:
    for option, value in (("--json", args.json), ("--screenshot", args.screenshot)):
        if value and not args.simulate:
            raise FacelabError(f"{option} goes with --simulate FILE.wav (a served session "
                               "records each turn's figures in its turn.json)")  # fmt: skip
    if args.simulate:
        from facelab.experiment.live_dialogue.simulate import simulate_live

        if args.input not in (None, "mic"):
            raise FacelabError("--simulate FILE is the talker: leave out --input")
        wav = Path(args.simulate)
        if not wav.is_file():
            raise FacelabError(f"--simulate {wav}: no such audio file")
        out = output_file(args.json, option="--json", force=True) if args.json else None
        shot = output_file(args.screenshot, option="--screenshot", force=True) \
            if args.screenshot else None  # fmt: skip
        config = _config(args)
        record = simulate_live(config, wav=wav, screenshot=shot)
        text = json.dumps(record, ensure_ascii=False, indent=2) + "\n"
        if out is not None:
            out.write_text(text, encoding="utf-8")
        print(
            f"live turn of {record['duration_s']} s under {args.condition!r}: mouth behind "
            f"sound median {record['latency_ms_median']} ms, p95 {record['latency_ms_p95']} ms"
            f" (budget {record['budget']['behind_ms_p95']:g} ms); {record['frames_shown']} "
            f"frames shown, {record['frames_late']} late; recorded in {record['recording']}"
        )
        if out is not None:
            print(f"wrote {out}")
        return 0
    return _serve(args)


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from facelab.experiment.live_dialogue.app import LiveHub, create_live_app

    hub = LiveHub.open(_config(args))
    url = f"http://{args.host}:{args.port}"
    print(f"facelab live: condition {args.condition!r}, {len(hub.driver.names)} channels; "
          f"turns recorded in {hub.config.session}")  # fmt: skip
    print(f"  viewer: {url}/")
    if hub.config.talker == "mic":
        print(f"  talker: {url}/talk  (a microphone page; browsers allow it on localhost or "
              "over https)")  # fmt: skip
    else:
        print(f"  talker: {hub.config.talker}, streamed when the first viewer connects")
    uvicorn.run(create_live_app(hub), host=args.host, port=args.port, log_level="warning")
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add("live", "a talker's voice drives the avatar live: viewers see and hear it, each "
            "turn recorded", _cmd_live)  # fmt: skip
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--condition", required=True, metavar="NAME",
                   help="the condition whose method drives the avatar")  # fmt: skip
    p.add_argument("--input", metavar="mic|FILE.wav", default=None,
                   help="the talker: 'mic' (default; the /talk page's microphone) or a file "
                   "the server streams in real time")  # fmt: skip
    p.add_argument("--display", choices=["live3d", "webxr", "window"], default="live3d",
                   help="how viewers see the avatar (default live3d: a browser page)")  # fmt: skip
    p.add_argument("--session", metavar="DIR",
                   help="where turns are recorded (default results/<study>/live/<condition>)")
    p.add_argument("--playout-ms", type=real(lo=40, hi=1000), default=120.0, metavar="MS",
                   help="the viewer hears the talker this long after the sound arrives "
                   "(room for the analysis and the network; default 120)")  # fmt: skip
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=whole(lo=1, hi=65535), default=8010, help="port (default 8010)")
    p.add_argument("--simulate", metavar="FILE.wav",
                   help="talker and viewer in headless Chromium, the file as the microphone; "
                   "one turn, its latency reported, then exit")  # fmt: skip
    p.add_argument("--json", metavar="FILE", help="--simulate: write the turn's figures here")
    p.add_argument("--screenshot", metavar="PNG", help="--simulate: the viewer mid-turn")
