"""The ``facelab`` command line: one subcommand per stage.

Exit status: 0 success; 2 a user mistake (bad protocol, option, file), reported as one clear
message without a traceback; 3 a stage that is not built in this version; 130 interrupted.
This is the only module that reads the process environment and turns paths from the user
into objects for the pure modules.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from experiment.errors import FacelabError, NotBuiltError

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


# --------------------------------------------------------------------------- stages to come


def _not_built(stage: str, issue: str) -> Handler:
    def handler(args: argparse.Namespace) -> int:
        raise NotBuiltError(
            f"'facelab {stage}' is not built yet in facelab {_version()} ({issue}); "
            "nothing was done"
        )

    return handler


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
        "render",
        "render every clip a protocol needs and write clips.csv",
        _not_built("render", "issue: avatar and rendering"),
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--out", metavar="DIR", help="clip folder (default results/<study>/clips)")
    p.add_argument("--contact-sheet", action="store_true", help="also write one PNG per condition")

    p = add(
        "run",
        "run a participant session in a PsychoPy window",
        _not_built("run", "issue: participant sessions"),
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participant", required=True, metavar="ID")
    p.add_argument("--session", type=int, default=1, metavar="N")
    p.add_argument("--resume", action="store_true", help="continue an interrupted session")
    p.add_argument("--windowed", action="store_true")
    p.add_argument(
        "--simulate", action="store_true", help="a scripted participant drives the window"
    )

    p = add(
        "simulate",
        "write complete sessions of simulated participants",
        _not_built("simulate", "issue: participant sessions"),
    )
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participants", type=int, default=8, metavar="N")
    p.add_argument("--seed", type=int, metavar="S")

    p = add(
        "analyze",
        "analyse session logs into tables, figures and a report",
        _not_built("analyze", "issue: analysis"),
    )
    p.add_argument("results", metavar="RESULTS")
    p.add_argument("--protocol", required=True, metavar="PROTOCOL")
    p.add_argument("--method", choices=["rm", "paper"], default="rm")

    p = add(
        "power",
        "implied effect size and participants needed for a chosen power",
        _not_built("power", "issue: analysis"),
    )

    p = add(
        "measure-z",
        "compute a Z matrix from face-capture CSV files",
        _not_built("measure-z", "issue: speech to animation"),
    )
    p.add_argument("captures", nargs="+", metavar="CAPTURE")

    p = add(
        "demo",
        "the whole study on the embedded defaults: render, simulate, analyse, report",
        _not_built("demo", "issue: end to end"),
    )
    p.add_argument("--out", metavar="DIR")

    p = add(
        "bench",
        "benchmarks that print JSON (visemes, render)",
        _not_built("bench", "issues: speech to animation; avatar and rendering"),
    )
    p.add_argument("what", choices=["visemes", "render"])
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
