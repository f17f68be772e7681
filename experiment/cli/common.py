"""Helpers shared by the command modules: option parsing and the registration signature."""

from __future__ import annotations

import argparse
import functools
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from facelab.errors import FacelabError

__all__ = [
    "AddCommand",
    "GridProgress",
    "Handler",
    "cluster_of",
    "cluster_options",
    "deprecated",
    "force_option",
    "output_dir",
    "output_file",
    "parse_session",
    "parse_size",
    "protocol_argument",
    "protocol_of",
    "real",
    "seed",
    "verbs",
    "whole",
]

Handler = Callable[[argparse.Namespace], int]
#: ``add(name, help, handler) -> parser``: what each family's ``register`` receives.
AddCommand = Callable[[str, str, Handler], argparse.ArgumentParser]


def verbs(parser: argparse.ArgumentParser) -> Callable[[str, str], argparse.ArgumentParser]:
    """Nested sub-commands (``facelab impression fit …``): ``verb(name, help)`` returns the
    verb's own parser, so an option of one verb is an error on another. The verb is
    ``args.action``."""
    sub = parser.add_subparsers(dest="action", metavar="VERB", required=True)

    def verb(name: str, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(verb_parser=p)  # errors after parsing name this verb's usage
        return p

    return verb


def force_option(parser: argparse.ArgumentParser) -> None:
    """The one overwrite rule: an output file (or analysis folder) that exists is replaced
    only with ``--force``."""
    parser.add_argument(
        "--force", action="store_true", help="replace output files that already exist"
    )


class _Deprecated(argparse.Action):
    """An old spelling of an option: stores into the new one's ``dest`` and says so once."""

    def __init__(self, option_strings: list[str], dest: str, *, new: str, **kw: object):
        self.new = new
        super().__init__(option_strings, dest, **kw)  # type: ignore[arg-type]

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # type: ignore[no-untyped-def]
        import sys

        print(
            f"facelab {parser.prog.split(maxsplit=1)[-1]}: {option_string} is deprecated; use "
            f"{self.new} (the old spelling works for this release)",
            file=sys.stderr,
        )
        setattr(namespace, self.dest, values)
        used = list(getattr(namespace, "deprecated_spellings", None) or [])
        namespace.deprecated_spellings = [*used, (option_string, self.new)]


def deprecated(
    parser: argparse.ArgumentParser, old: str, *, new: str, dest: str, **kw: object
) -> None:
    """Accept ``old`` for one release as a spelling of ``new`` (which stores into ``dest``),
    with a deprecation message on stderr; hidden from ``--help``."""
    parser.add_argument(old, action=_Deprecated, new=new, dest=dest, help=argparse.SUPPRESS, **kw)


def protocol_argument(parser: argparse.ArgumentParser, *, optional: bool = False) -> None:
    """The protocol as the command's first positional (one grammar for every command that
    works on one protocol); ``--protocol P``, the old spelling, still works for one release.
    Read it with :func:`protocol_of`."""
    parser.add_argument(
        "protocol", nargs="?" if optional else None, metavar="PROTOCOL", help="protocol YAML"
    )
    deprecated(parser, "--protocol", new="the PROTOCOL positional", dest="old_protocol")


def protocol_of(args: argparse.Namespace) -> str | None:
    """The protocol named by the positional or the deprecated ``--protocol``."""
    given = getattr(args, "protocol", None)
    old = getattr(args, "old_protocol", None)
    if given and old and given != old:
        raise FacelabError(f"two protocols given: {given} and --protocol {old}; give one")
    return given or old


def seed(value: str) -> int:
    """``--seed S``: an integer 0 <= S < 2**63, as the protocol's ``seed`` (argparse type)."""
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {value!r}") from None
    if not 0 <= number < 2**63:
        raise argparse.ArgumentTypeError(f"seeds are whole numbers 0..2**63-1, got {value}")
    return number


def whole(*, lo: int, hi: int | None = None) -> Callable[[str], int]:
    """argparse type: a whole number ``lo <= n [<= hi]``; the message names the range."""

    def parse(value: str) -> int:
        try:
            number = int(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {value!r}") from None
        if number < lo or (hi is not None and number > hi):
            span = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            raise argparse.ArgumentTypeError(f"expected a whole number {span}, got {value}")
        return number

    return parse


def real(
    *, lo: float | None = None, hi: float | None = None, above: float | None = None,
    below: float | None = None,
) -> Callable[[str], float]:  # fmt: skip
    """argparse type: a finite number, ``lo <= x <= hi`` / ``above < x < below`` where given."""

    def parse(value: str) -> float:
        try:
            number = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {value!r}") from None
        if not math.isfinite(number):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {value}")
        wrong = []
        if lo is not None and number < lo:
            wrong.append(f">= {lo:g}")
        if hi is not None and number > hi:
            wrong.append(f"<= {hi:g}")
        if above is not None and number <= above:
            wrong.append(f"> {above:g}")
        if below is not None and number >= below:
            wrong.append(f"< {below:g}")
        if wrong:
            raise argparse.ArgumentTypeError(
                f"expected a number {' and '.join(wrong)}, got {value}"
            )
        return number

    return parse


MAX_SIZE = (7680, 4320)  # as the protocol's rendering.width/height allow


def parse_size(
    text: str | None, *, option: str = "--size", largest: tuple[int, int] | None = MAX_SIZE
) -> tuple[int, int] | None:
    """``WIDTHxHEIGHT`` -> (width, height); even numbers >= 64 (H.264 needs even sizes), at
    most ``largest`` (8K by default, the largest frame a protocol may render; None for a
    window, which may span several screens); None when the flag was not given (an empty
    value is an error); ``option``: the flag the errors name."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise FacelabError(f"{option} {text!r}: expected WIDTHxHEIGHT, e.g. 640x360") from None
    if w % 2 or h % 2 or w < 64 or h < 64:
        raise FacelabError(f"{option} {text!r}: width and height must be even and >= 64")
    if largest is not None and (w > largest[0] or h > largest[1]):
        raise FacelabError(f"{option} {text!r}: expected at most {largest[0]}x{largest[1]}")
    return w, h


def parse_session(value: str) -> int:
    """``--session N``: an integer 1..9999 (argparse type)."""
    from facelab.sessionlog import MAX_SESSION

    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a session number, got {value!r}") from None
    if not 1 <= number <= MAX_SESSION:
        raise argparse.ArgumentTypeError(f"sessions are numbered 1..{MAX_SESSION}, got {value}")
    return number


def _writable_folder(folder: Path, option: str, what: str) -> None:
    probe = folder
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise FacelabError(f"{option} {what}: {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise FacelabError(f"{option} {what}: cannot write in {probe} (permission denied)")


@functools.cache
def figure_suffixes() -> tuple[str, ...]:
    """File name endings of the figures facelab draws with Matplotlib: every format its
    canvas writes (.png, .svg, .pdf, .eps, .tif, .jpg, …)."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted(f".{k}" for k in FigureCanvasBase.get_supported_filetypes()))


@functools.cache
def picture_suffixes() -> tuple[str, ...]:
    """File name endings of the RGB pictures facelab saves with Pillow (contact sheets): the
    common raster formats and PDF, as far as this Pillow writes them."""
    from PIL import Image

    Image.init()
    writes = {ext for ext, fmt in Image.registered_extensions().items() if fmt in Image.SAVE}
    common = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".bmp", ".pdf")
    return tuple(ext for ext in common if ext in writes)


def output_file(
    path: str | Path,
    *,
    option: str,
    force: bool,
    suffixes: tuple[str, ...] | Callable[[], tuple[str, ...]] = (),
) -> Path:
    """A file the command will write: its folder must exist and be writable, an existing
    file is refused unless ``force`` (the one overwrite rule, ``--force``), and with
    ``suffixes`` its name must end in one of them (a figure's format). Raises a clear error
    (exit 2) before the command writes anything, instead of a traceback half-way through.
    """
    path = Path(path)
    if path.is_dir():
        raise FacelabError(f"{option} {path}: is a folder; give a file name")
    if not path.parent.is_dir():
        raise FacelabError(f"{option} {path}: the folder {path.parent} does not exist")
    _writable_folder(path.parent, option, str(path))
    if callable(suffixes):
        suffixes = suffixes()
    if suffixes and path.suffix.lower() not in suffixes:
        *most, last = suffixes
        ending = f"{', '.join(most)} or {last}" if most else last
        raise FacelabError(
            f"{option} {path}: expected a file name ending in {ending} (the picture's format)"
        )
    if path.exists() and not force:
        raise FacelabError(f"{option} {path}: exists; choose another file or pass --force")
    return path


def output_dir(path: str | Path, *, option: str) -> Path:
    """A folder the command will create or write into (parents are created)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FacelabError(f"{option} {path}: is a file, not a folder")
    _writable_folder(path, option, str(path))
    return path


def parse_effects(pairs: list[str] | None) -> dict[str, float] | None:
    """``--effect COND=POINTS`` options as ``{condition: points}`` (None when none given)."""
    if not pairs:
        return None
    effects: dict[str, float] = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            effects[name] = float(value)
            if not math.isfinite(effects[name]):
                raise ValueError
        except ValueError:
            raise FacelabError(
                f"--effect {pair!r}: expected CONDITION=POINTS with POINTS a finite number "
                "(rating points), e.g. standard=15"
            ) from None
    return effects


class GridProgress:
    """One bar over a grid of clips or simulations: done / failed / retried and the ETA, on a
    terminal; nothing when ``quiet`` or when stderr is not a terminal (logs and pipes get the
    per-clip lines and the closing summary instead of escape codes).

    Call :meth:`start` with the number of tasks, pass the instance as a grid's ``progress``
    callback, and call :meth:`close` at the end."""

    def __init__(self, *, quiet: bool, prefix: str = "", unit: str = "clip") -> None:
        import sys

        self._enabled = not quiet and sys.stderr.isatty()
        self._prefix = prefix
        self._unit = unit
        self._bar = None

    def start(self, total: int) -> None:
        self.close()
        if self._enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=self._prefix or None, unit=self._unit)

    def __call__(self, key: str, event: str, done: int, failed: int, retried: int) -> None:
        if self._bar is not None:
            self._bar.update(1)
            self._bar.set_postfix_str(f"{event} {key[:32]}; failed {failed}", refresh=False)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def cluster_options(parser: argparse.ArgumentParser, *, what: str = "clips") -> None:
    """``--workers N`` / ``--scheduler ADDRESS``: where a grid's tasks run (default here)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--workers",
        type=whole(lo=1, hi=512),
        metavar="N",
        help=f"render/simulate the {what} on a local Dask cluster of N single-thread worker "
        "processes (default: serially in this process)",
    )
    group.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help=f"send the {what} to a running Dask scheduler, e.g. tcp://host:8786 (its workers "
        "started with `dask worker ADDRESS`; see the README's cluster section)",
    )


def cluster_of(args: argparse.Namespace):
    """The :class:`facelab.grid.Cluster` the options ask for."""
    from facelab.grid import Cluster

    return Cluster(
        workers=getattr(args, "workers", None), scheduler=getattr(args, "scheduler", None)
    )


def check_options(parser: argparse.ArgumentParser) -> None:
    """``--accept-check NAME[:CLIP]`` (repeatable): a stimulus check whose failures (or one
    clip's, as the failure line names it) are recorded instead of stopping the command."""
    from facelab.protocol_checks import CHECK_NAMES, accept_name_problem

    def check_name(text: str) -> str:
        if (problem := accept_name_problem(text)) is not None:
            raise argparse.ArgumentTypeError(problem)
        return text

    parser.add_argument(
        "--accept-check", action="append", default=[], metavar="NAME[:CLIP]", type=check_name,
        help="accept the failures of this stimulus check, or with :CLIP of one clip as the "
        "failure names it (recorded in clips.csv and stimulus_checks.csv): "
        f"{', '.join(CHECK_NAMES)}",
    )  # fmt: skip


#: this many clips or more with the same warning are said in one line
GROUP_WARNINGS_FROM = 4


def say_checks(report, *, say: Callable[[str], None] = print) -> None:
    """Every warning and accepted failure of a stimulus-check report, then its summary. The
    same warning on many clips (a check, measure, value and note alike, e.g. a face too small
    for the tracker at a demo's size) is one line naming the first clips and how many more:
    every row stays in ``stimulus_checks.csv``."""
    groups: dict[tuple[bool, str, str], list] = {}
    for row in report.warnings:
        groups.setdefault((row.accepted, row.check, row.what()), []).append(row)
    for (accepted, check, what), rows in groups.items():
        mark = "accepted: " if accepted else "warning: "
        if len(rows) < GROUP_WARNINGS_FROM:
            for row in rows:
                say(mark + row.describe())
            continue
        first = ", ".join(row.where() for row in rows[:2])
        say(f"{mark}{check}: {len(rows)} clips ({first} and {len(rows) - 2} more; each in "
            f"stimulus_checks.csv): {what}")  # fmt: skip
    say(report.summary())


def run_stimulus_checks(
    protocol, *, protocol_path: Path, clips_dir: Path, accept: Sequence[str],
    say: Callable[[str], None] = print, sheets: bool = False,
):  # fmt: skip
    """The stimulus checks of rendered clips (``facelab check`` and the end of ``render``):
    writes ``stimulus_checks.csv``, marks ``clips.csv``, prints the summary and every
    warning; with ``sheets``, draws the contact sheets marked with the results (also when a
    check failed, so the failure can be looked at); then raises the StageError naming each
    failure (exit 2) unless accepted."""
    from facelab.stimuli.checks.run_checks import check_clips, record_in_manifest
    from facelab.stimuli.render.contact_sheets import contact_sheets

    report = check_clips(protocol, protocol_path=protocol_path, clips_dir=clips_dir,
                         accept=accept, log=say)  # fmt: skip
    record_in_manifest(clips_dir, report)
    say_checks(report, say=say)
    if sheets:
        drawn = contact_sheets(protocol, protocol_path=protocol_path, out=clips_dir)
        report.notes += [f"contact sheet: {p}" for p in drawn]
        say("contact sheets (marked with the checks): " + ", ".join(str(p) for p in drawn))
    if report.failures:
        raise report.error()
    return report


def conversation_talker(args: argparse.Namespace, protocol: Any) -> str | Path | None:
    """``--conversation-input`` checked against the protocol: the talker of its
    ``presentation.conversation`` (a file, or ``"mic"``: the talker's page), None without one
    (FacelabError for a file given to a protocol with none, or a missing file)."""
    given = args.conversation_input
    if protocol.presentation.conversation is None:
        if given is not None:
            raise FacelabError(f"--conversation-input: {args.protocol} has no "
                               "presentation.conversation")  # fmt: skip
        return None
    if given is not None and not Path(given).is_file():
        raise FacelabError(f"--conversation-input {given}: no such file")
    return Path(given) if given is not None else "mic"


def add_conversation_options(p: argparse.ArgumentParser, *, who: str) -> None:
    """``--conversation-input`` and ``--conversation-playout-ms`` (``who`` hears the talker)."""
    p.add_argument(
        "--conversation-input",
        metavar="FILE.wav",
        help="presentation.conversation: the server is the talker, saying this recording "
        "once the conversation starts (demos and tests); default: the talker's page /talk, "
        "with a microphone",
    )
    p.add_argument(
        "--conversation-playout-ms", type=real(lo=40, hi=1000), default=120.0, metavar="MS",
        help=f"{who} hears the talker this long after the sound arrives (a jitter buffer that "
        "also holds the analysis; default 120)",
    )  # fmt: skip
