"""Protocol commands: ``validate``, ``design``, ``schema``, ``protocols``."""

from __future__ import annotations

import argparse
import sys

from facelab.errors import FacelabError
from facelab.experiment.cli.common import AddCommand, output_dir, output_file, seed


def _cmd_validate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from facelab.design import count_trials
    from facelab.experiment.timeline import vr_wording_notes
    from facelab.protocol import load_protocol

    try:
        from facelab.stimuli.render.inputs import input_notes, load_checked_protocol
    except ImportError:  # the core alone: the files the protocol names are not read
        load_checked_protocol = input_notes = None
        print("note: files named by the protocols are not checked (needs facelab[stimuli])")
    for path in args.protocols:
        protocol = (load_protocol(path) if load_checked_protocol is None
                    else load_checked_protocol(path))  # fmt: skip
        if input_notes is not None:
            for note in input_notes(protocol, base_dir=Path(path).parent):
                print(f"{path}: {note}")
            _audit(protocol, path=Path(path))
        n_trials = count_trials(protocol)
        print(
            f"ok: {path}: study {protocol.study.id!r}, {len(protocol.conditions)} conditions, "
            f"{sum(len(s.stimuli) for s in protocol.stimulus_sets)} stimuli in "
            f"{len(protocol.stimulus_sets)} sets, {len(protocol.blocks)} blocks, "
            + (
                f"{n_trials} trials x {len(protocol.items)} items per participant"
                if not protocol.tasks
                else f"{n_trials} trials per participant; tasks: "
                + ", ".join(f"{t.id} ({t.type})" for t in protocol.tasks)
            )
            + _plugins_used(protocol)
        )
        for note in _simulation_notes(protocol) + vr_wording_notes(protocol):
            print(f"{path}: note: {note}")
    return 0


def _plugins_used(protocol) -> str:
    """What the protocol takes from installed packages (methods, screen kinds), said so a
    plugin's use is confirmed."""
    from facelab.methods import BUILTIN_METHODS
    from facelab.plugins import GROUPS, plugin_entries

    packages = {e.name: e.package for e in plugin_entries(GROUPS["methods"])}
    packages |= {e.name: e.package for e in plugin_entries(GROUPS["screens"])}
    methods = sorted({c.method for c in protocol.conditions} - set(BUILTIN_METHODS))
    kinds = [s.kind for s in protocol.presentation.added_screens]
    said = [f"method {m} ({packages.get(m, '?')})" for m in methods]
    said += [f"screen kind {k} ({packages.get(k, '?')})" for k in kinds]
    return f"; from packages: {', '.join(said)}" if said else ""


def _simulation_notes(protocol) -> list[str]:
    """Conditions the simulated participants treat as the baseline only because the protocol
    gives them no effect (``simulation.effects``): said, not assumed silently."""
    effects = protocol.simulation.effects
    if not effects:
        return []
    missing = [c.id for c in protocol.conditions if c.id not in effects]
    if not missing:
        return []
    return [f"simulation.effects gives no effect for {', '.join(missing)}: simulated "
            "participants rate them with effect 0 (as the baseline)"]  # fmt: skip


def _audit(protocol, *, path) -> None:
    """The stimulus checks' avatar audit (geometry only): warnings printed, failures refused
    unless the protocol accepts them (``checks.accept``)."""
    from facelab.errors import StageError
    from facelab.stimuli.checks.avatar_checks import audit_avatar
    from facelab.stimuli.checks.rows import accept_checks
    from facelab.stimuli.render.scene import load_avatar

    avatar = load_avatar(protocol, base_dir=path.parent)
    rows = accept_checks(audit_avatar(avatar, protocol, base_dir=path.parent),
                         protocol.checks.accept)  # fmt: skip
    for row in rows:
        if row.passed is False and not row.failed:
            print(f"{path}: {'accepted' if row.accepted else 'warning'}: {row.describe()}")
    failures = [r for r in rows if r.failed]
    if failures:
        raise StageError(
            f"{path}: the avatar cannot show what the protocol asks (stimulus check "
            "avatar_audit):\n"
            + "\n".join(f"  {r.describe()}" for r in failures)
            + "\nre-export the avatar with these shapes, or accept with "
            "'checks: {accept: [avatar_audit]}' in the protocol"
        )


def _cmd_design(args: argparse.Namespace) -> int:
    from facelab.design import build_trials, trials_frame
    from facelab.protocol import load_protocol

    protocol = load_protocol(args.protocol)
    frame = trials_frame(build_trials(protocol, participant=args.participant, seed=args.seed))
    if args.out:
        out = output_file(args.out, option="--out", force=args.force)
        frame.to_csv(out, index=False)
        print(f"wrote {len(frame)} trials to {out}", file=sys.stderr)
    else:
        frame.to_csv(sys.stdout, index=False, lineterminator="\n")
    return 0


def _cmd_schema(args: argparse.Namespace) -> int:
    from facelab.protocol import schema_json_text

    text = schema_json_text()
    if args.out:
        output_file(args.out, option="--out", force=args.force).write_text(text, encoding="utf-8")
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def _cmd_plugins(args: argparse.Namespace) -> int:
    """Every plugin installed packages declare, by group, with its package and state."""
    from facelab.plugins import GROUPS, plugin_entries
    from facelab.stimuli.methods import load_plugins

    load_plugins()  # checks what each plugin names, recording problems
    from facelab.experiment.screen_kinds import load_screen_plugins

    load_screen_plugins()
    broken = 0
    for kind, group in GROUPS.items():
        entries = plugin_entries(group)
        print(f"{kind} (entry points {group}): {len(entries) or 'none installed'}")
        for entry in entries:
            print(f"  {entry.describe()}")
            broken += entry.problem is not None
    if broken:
        print(f"{broken} plugin(s) could not be used; the rest of facelab works without them",
              file=sys.stderr)  # fmt: skip
    return 1 if broken else 0


def _cmd_protocols(args: argparse.Namespace) -> int:
    from facelab.protocol import load_protocol
    from facelab.resources import copy_protocol, shipped_protocols

    if args.name and args.copy and args.name != args.copy:
        raise FacelabError(
            f"protocols: NAME {args.name!r} and --copy {args.copy!r} disagree; give one"
        )
    name = args.name or args.copy
    if name:
        written = copy_protocol(name, output_dir(args.to, option="--to"), force=args.force)
        for path in written:
            print(f"wrote {path}")
        print(f"edit {written[0]}, then: facelab validate {written[0]}", file=sys.stderr)
        return 0
    for name, path in shipped_protocols().items():
        protocol = load_protocol(path)
        print(f"{name:<24} {protocol.study.title}  ({path})")
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add("validate", "check protocol files; print a summary of each", _cmd_validate)
    p.add_argument("protocols", nargs="+", metavar="PROTOCOL", help="protocol YAML file(s)")

    p = add("design", "print a participant's ordered trial list as CSV", _cmd_design)
    p.add_argument("protocol", metavar="PROTOCOL")
    p.add_argument("--participant", required=True, metavar="ID", help="participant id, e.g. P01")
    p.add_argument("--seed", type=seed, metavar="N", help="study seed instead of the protocol's")
    p.add_argument("--out", metavar="FILE", help="write the CSV to FILE instead of stdout")
    p.add_argument("--force", action="store_true", help="replace FILE if it exists")

    add("plugins", "list the installed plugins (methods, screen kinds) and their packages",
        _cmd_plugins)  # fmt: skip

    p = add("schema", "print the protocol JSON Schema (as in protocols/schema/)", _cmd_schema)
    p.add_argument("--out", metavar="FILE", help="write to FILE instead of stdout")
    p.add_argument("--force", action="store_true", help="replace FILE if it exists")

    p = add(
        "protocols",
        "list the protocols shipped with facelab, or copy one out for editing",
        _cmd_protocols,
    )
    p.add_argument(
        "name", nargs="?", metavar="NAME", help="copy the shipped protocol NAME (and its files)"
    )
    p.add_argument("--copy", metavar="NAME", help="the same as NAME")
    p.add_argument("--to", default=".", metavar="DIR", help="folder to copy into (default .)")
    p.add_argument("--force", action="store_true", help="replace files that exist")
