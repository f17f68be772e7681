"""Live dialogue: ``facelab live`` (a talker's voice drives the avatar as it streams)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    output_file,
    parse_size,
    real,
    whole,
)


def _config(args: argparse.Namespace):
    from facelab.experiment.live_dialogue.app import LiveConfig
    from facelab.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    ids = [c.id for c in protocol.conditions]
    if args.condition not in ids:
        raise FacelabError(f"--condition {args.condition}: the protocol's conditions are "
                           f"{', '.join(ids)}")  # fmt: skip
    talker: str | Path = "mic"
    if args.input not in (None, "mic"):
        talker = Path(args.input)
        if not talker.is_file():
            raise FacelabError(f"--input {talker}: no such audio file (or give 'mic')")
    if args.display == "window":  # before anything starts: the participant must hear it
        from facelab.experiment.live_dialogue.app import LIVE_RATE
        from facelab.experiment.live_dialogue.window_view import SoundOut

        SoundOut.check(sample_rate=LIVE_RATE)
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
        shot = output_file(args.screenshot, option="--screenshot", force=True,
                           suffixes=(".png",)) if args.screenshot else None  # fmt: skip
        config = _config(args)
        record = simulate_live(config, wav=wav, screenshot=shot, window_size=_window_size(args))
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


def _window_size(args: argparse.Namespace) -> tuple[int, int]:
    for option, value in (("--size", args.size), ("--windowed", args.windowed)):
        if value and args.display != "window":
            raise FacelabError(f"{option} goes with --display window (the lab window)")
    return parse_size(args.size, largest=None) or (1280, 800)  # a window


def _serve(args: argparse.Namespace) -> int:
    import uvicorn

    from facelab.experiment.live_dialogue.app import LiveHub, create_live_app

    size = _window_size(args)
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
    if args.display == "window":
        return _serve_window(hub, args, size=size)
    uvicorn.run(create_live_app(hub), host=args.host, port=args.port, log_level="warning")
    return 0


def _serve_window(hub, args: argparse.Namespace, *, size: tuple[int, int]) -> int:
    """The server in a thread, the lab window (this thread) its viewer until Escape."""
    from facelab.experiment.live_dialogue.app import create_live_app
    from facelab.experiment.live_dialogue.window_view import WindowViewer
    from facelab.experiment.online.serve import BackgroundServer

    fullscreen = hub.config.protocol.presentation.fullscreen and not args.windowed
    with BackgroundServer(None, host=args.host, port=args.port, app=create_live_app(hub)):
        loop = hub.running_loop()
        print("  the lab window shows the avatar; Escape (then y) closes it")
        with WindowViewer(hub, loop=loop, size=size, fullscreen=fullscreen) as view:
            shown = view.run()
    print(f"facelab live: {shown['turns_shown']} turns shown in the window; "
          f"{len(hub.turns)} recorded in {hub.config.session}")  # fmt: skip
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
                   help="how viewers see the avatar (default live3d: a browser page; "
                   "window: the lab machine's window and speakers)")  # fmt: skip
    p.add_argument("--session", metavar="DIR",
                   help="where turns are recorded (default results/<study>/live/<condition>)")
    p.add_argument("--playout-ms", type=real(lo=40, hi=1000), default=120.0, metavar="MS",
                   help="the viewer hears the talker this long after the sound arrives "
                   "(room for the analysis and the network; default 120)")  # fmt: skip
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=whole(lo=1, hi=65535), default=8010, help="port (default 8010)")
    p.add_argument("--simulate", metavar="FILE.wav",
                   help="the talker page in headless Chromium, the file as its microphone, and "
                   "the viewer (Chromium, or the lab window with --display window); one turn, "
                   "its latency reported, then exit")  # fmt: skip
    p.add_argument("--json", metavar="FILE", help="--simulate: write the turn's figures here")
    p.add_argument("--screenshot", metavar="PNG", help="--simulate: the viewer mid-turn")
    p.add_argument("--windowed", action="store_true",
                   help="--display window: a window instead of the protocol's full screen")
    p.add_argument("--size", metavar="WxH",
                   help="--display window: the window's size (default 1280x800)")
