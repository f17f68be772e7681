"""The ``facelab`` command line: one subcommand per stage, one module per command family.

Exit status: 0 success; 2 a user mistake (bad protocol, option, file), reported as one clear
message without a traceback; 4 a session stopped by the experimenter (ratings kept);
130 interrupted (SIGINT), 143 terminated (SIGTERM), 129 hung up (SIGHUP).
The command modules are the only place that reads the process environment and turns paths
from the user into objects for the pure modules. Each family module has ``register(add)``;
a new family is one module and one line in :data:`FAMILIES`.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence

from facelab import __version__
from facelab.errors import FacelabError
from facelab.experiment.cli import (
    analysis_cmds,
    avatar_cmds,
    behaviour_cmds,
    demo_cmd,
    impression_cmds,
    latency_cmds,
    live_cmds,
    online_cmds,
    protocol_cmds,
    session_cmds,
    stimulus_cmds,
)
from facelab.experiment.cli.common import Handler

__all__ = ["main"]

#: Command families, in the order ``facelab --help`` lists them.
FAMILIES = (
    protocol_cmds,
    stimulus_cmds,
    avatar_cmds,
    impression_cmds,
    behaviour_cmds,
    session_cmds,
    online_cmds,
    live_cmds,
    latency_cmds,
    analysis_cmds,
    demo_cmd,
)


def build_parser() -> argparse.ArgumentParser:
    """The `facelab` command line: every verb its family module registers."""
    parser = argparse.ArgumentParser(
        prog="facelab",
        description="Perception experiments on talking 3D avatar heads: one protocol file -> "
        "rendered clips -> participant sessions with VAS ratings -> analysis and report.",
    )
    parser.add_argument("--version", action="version", version=f"facelab {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name: str, help_text: str, handler: Handler) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(handler=handler, verb_parser=p)
        return p

    for family in FAMILIES:
        family.register(add)
    return parser


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived: unwind like Ctrl-C (files closed, responses kept)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_terminated(signum: int, _frame: object) -> None:
    raise Terminated(signum)


#: top-level import names of the optional dependencies -> the extra that installs them
_EXTRA_OF = {
    **dict.fromkeys(
        ["pyopenjtalk", "pygltflib", "soundfile", "sklearn", "pympi", "PIL"], "stimuli"
    ),
    **dict.fromkeys(["pyrender", "trimesh", "OpenGL"], "render"),
    "psychopy": "runner",
    **dict.fromkeys(
        ["fastapi", "uvicorn", "sqlalchemy", "alembic", "psycopg", "selenium", "httpx2"], "online"
    ),
    "pylipsync": "bench",
}


def _parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """The arguments, with the errors argparse leaves to the top-level parser said by the
    verb's own parser (its usage): unknown options, an option given in its old and new
    spelling at once; a PROTOCOL naming a shipped protocol (``kato2021``) that is not a file
    here is the shipped file."""
    given = list(sys.argv[1:] if argv is None else argv)
    args, extra = parser.parse_known_args(given)
    verb = getattr(args, "verb_parser", parser)
    if extra:
        verb.error(f"unrecognized arguments: {' '.join(extra)}")
    for old, new in getattr(args, "deprecated_spellings", None) or []:
        if any(a == new or a.startswith(f"{new}=") for a in given):
            verb.error(f"{old} and {new} are one option (the old and the new spelling); "
                       f"give {new} once")  # fmt: skip
    for name in ("protocol", "protocols"):
        value = getattr(args, name, None)
        if isinstance(value, str):
            setattr(args, name, _shipped_or_given(value))
        elif isinstance(value, list):
            setattr(args, name, [_shipped_or_given(v) for v in value])
    return args


def _shipped_or_given(value: str) -> str:
    """A shipped protocol's file for a bare name that is not a file here, else ``value``."""
    from pathlib import Path

    from facelab.resources import shipped_protocols

    if Path(value).exists() or "/" in value or value.endswith((".yaml", ".yml")):
        return value
    found = shipped_protocols().get(value)
    return str(found) if found is not None else value


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = _parse(parser, argv)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGTERM, signal.SIGHUP):
            previous[signum] = signal.signal(signum, _raise_terminated)
    try:
        return int(args.handler(args))
    except FacelabError as exc:
        print(f"facelab {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"facelab {args.command}: interrupted; what was saved is kept", file=sys.stderr)
        return 130
    except Terminated as exc:
        name = signal.Signals(exc.signum).name
        print(f"facelab {args.command}: stopped by {name}; what was saved is kept", file=sys.stderr)
        return 128 + exc.signum
    except BrokenPipeError:  # e.g. `facelab design ... | head`
        sys.stderr.close()
        return 0
    except OSError as exc:  # the system refused a file operation (a full disk, /proc, rights)
        if exc.errno is None:
            raise  # not the system's refusal: a bug to see in full
        files = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        print(
            f"facelab {args.command}: error: {files + ': ' if files else ''}the system refused "
            f"a file operation ({exc.strerror or 'no reason given'}); the command stopped there",
            file=sys.stderr,
        )
        return 2
    except ModuleNotFoundError as exc:
        extra = _EXTRA_OF.get((exc.name or "").split(".")[0])
        if extra is None:
            raise
        print(
            f"facelab {args.command}: error: this needs {exc.name!r}, from facelab's "
            f"{extra!r} extra, which is not installed: pip install 'facelab[{extra}]' (or "
            "'facelab[all]'; scripts/setup.sh installs everything)",
            file=sys.stderr,
        )
        return 3
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
