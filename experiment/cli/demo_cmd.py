"""``facelab demo``: the whole study on the embedded defaults."""

from __future__ import annotations

import argparse
from pathlib import Path

from facelab.experiment.cli.common import (
    AddCommand,
    GridProgress,
    check_options,
    deprecated,
    output_dir,
    parse_size,
    protocol_argument,
    protocol_of,
    seed,
    whole,
)


def _cmd_demo(args: argparse.Namespace) -> int:
    from facelab.experiment.demo import DEFAULT_PROTOCOL, run_demo

    size = parse_size(args.size)
    progress = GridProgress(quiet=args.quiet, prefix="render")

    try:
        run_demo(
            out=output_dir(args.out, option="--out"),
            protocol_path=Path(protocol_of(args) or DEFAULT_PROTOCOL),
            participants=args.participants,
            seed=args.sim_seed,
            size=size,
            fps=args.fps,
            progress=progress,
            accept=args.accept_check,
        )
    finally:
        progress.close()
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add(
        "demo",
        "the whole study on the embedded defaults: render, simulate, analyse, report",
        _cmd_demo,
    )
    p.add_argument(
        "--out", default="results/demo", metavar="DIR", help="output folder (default results/demo)"
    )
    protocol_argument(p, optional=True)  # default: the shipped kato2021
    p.add_argument("--participants", type=whole(lo=1, hi=5000), default=8, metavar="N")
    p.add_argument(
        "--sim-seed", type=seed, default=2021, metavar="S", help="seed of the simulated ratings"
    )
    deprecated(p, "--seed", new="--sim-seed", dest="sim_seed", type=seed)
    p.add_argument(
        "--size", metavar="WxH", help="override the resolution (e.g. 320x180 for a quick run)"
    )
    p.add_argument("--fps", type=whole(lo=1, hi=240), help="override the frame rate")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    check_options(p)
