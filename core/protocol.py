"""Protocol files: load, validate and cross-check a study's YAML into a frozen model.

:func:`load_protocol` reads a file and returns a frozen :class:`Protocol`, or raises
:class:`~facelab.errors.ProtocolError` listing every problem with the file, the line and
the key path, and what was expected. Nothing in a protocol is evaluated as code.

The pieces: the typed models (:mod:`facelab.protocol_model`), YAML with line numbers
(:mod:`facelab.protocol_yaml`) and the checks across sections
(:mod:`facelab.protocol_checks`). The models are re-exported here for convenience.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from functools import cache
from pathlib import Path
from typing import Any, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError, create_model

from facelab.errors import Issue, ProtocolError
from facelab.protocol_checks import clean_loc, cross_check, describe, pydantic_message
from facelab.protocol_model import (
    ID_PATTERN,
    LANG_PATTERN,
    SCHEMA_VERSION,
    VOWELS_PATTERN,
    AnyTask,
    Block,
    ChoiceTask,
    Condition,
    IdentifyTask,
    MatrixTask,
    Protocol,
    Rendering,
    StaircaseRule,
    Stimulus,
    StimulusSet,
    TypedTask,
    VasItem,
    json_schema,
    schema_json_text,
)
from facelab.protocol_yaml import Locator, YamlRefusedError, gc_paused, read_yaml

__all__ = [
    "SCHEMA_VERSION",
    "AnyTask",
    "Block",
    "ChoiceTask",
    "Condition",
    "IdentifyTask",
    "MatrixTask",
    "Protocol",
    "Rendering",
    "StaircaseRule",
    "Stimulus",
    "StimulusSet",
    "TypedTask",
    "VasItem",
    "json_schema",
    "load_protocol",
    "load_protocol_text",
    "protocol_hash",
    "schema_json_text",
]


def protocol_hash(path: Path | str) -> str:
    """SHA-256 of the protocol file's bytes, as logged with every session."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


#: more checks of a protocol that validated: ``(protocol, base_dir) -> issues`` (e.g. reading
#: every file it names, :func:`facelab.stimuli.render.inputs.input_problems`)
FileChecks = Callable[[Protocol, Path], Sequence[Issue]]


def load_protocol(path: Path | str, *, file_checks: FileChecks | None = None) -> Protocol:
    """Read, validate and cross-check a protocol file; ``file_checks`` add their problems to
    the same report whenever every section validated (a key's problem is said once, the
    first found), so a missing file does not hide an unreadable one.

    Raises
    ------
    ProtocolError
        With every problem found: file, line, key path and what was expected.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ProtocolError(path, [Issue((), "file not found")]) from None
    except UnicodeDecodeError as exc:
        raise ProtocolError(
            path,
            [Issue((), f"not UTF-8 text (byte {exc.start} is not; a binary file renamed "
                   "to .yaml?): a protocol is a YAML text file")],
        ) from None
    except OSError as exc:
        raise ProtocolError(
            path, [Issue((), f"cannot read the file ({exc.strerror or 'unreadable'})")]
        ) from None
    return load_protocol_text(text, path=path, base_dir=path.parent, file_checks=file_checks)


def load_protocol_text(
    text: str, *, path: Path | str, base_dir: Path, file_checks: FileChecks | None = None
) -> Protocol:
    """A protocol from its text (e.g. a stored copy of the file a session ran), files it names
    resolved against ``base_dir``; ``path`` names it in errors. See :func:`load_protocol`."""
    path = Path(path)
    try:
        root, data = read_yaml(text)
    except YamlRefusedError as exc:
        raise ProtocolError(path, [exc.issue]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc)
        where = text.splitlines()[line - 1] if line and line <= len(text.splitlines()) else ""
        if "\t" in where[: len(where) - len(where.lstrip())]:
            problem = "a tab indents this line; YAML indents with spaces only"
        raise ProtocolError(path, [Issue((), f"not valid YAML: {problem}", line)]) from None
    except RecursionError:  # pragma: no cover - the depth limit comes first
        raise ProtocolError(path, [Issue((), "nested too deeply")]) from None
    if root is None or not isinstance(data, dict):
        raise ProtocolError(path, [Issue((), "expected a YAML mapping with the study's sections")])

    with gc_paused():
        protocol, issues, locator, complete = _validate(path, root, data, base_dir=base_dir)
    if file_checks is not None and complete:  # with the collector on: they read files
        assert protocol is not None
        issues += _more_issues(file_checks, protocol, base_dir, issues, locator)
    if issues:
        raise ProtocolError(path, issues)
    assert protocol is not None
    return protocol


def _validate(
    path: Path, root: Any, data: dict[str, Any], *, base_dir: Path
) -> tuple[Protocol | None, list[Issue], Locator, bool]:
    """Every problem of the file at once: duplicate keys, then types, then the checks across
    sections on whatever validated. Returns the protocol (None when even the sections that
    validated do not make one), the problems, the key locator, and whether every section
    validated."""
    locator = Locator(root)
    issues = list(locator.duplicate_keys())
    protocol: Protocol | None = None
    available: set[str] = set(Protocol.model_fields)
    try:
        protocol = Protocol.model_validate(data)
    except ValidationError as exc:
        found: dict[tuple[str | int, ...], Issue] = {}
        failing: set[str] = set()
        for err in exc.errors():
            issue = _issue_from_pydantic(err, locator)
            found.setdefault(issue.path, issue)  # one message per key path
            if err["loc"]:
                failing.add(str(err["loc"][0]))
        issues += found.values()
        available -= failing
        protocol = _partial(data, available)
    if protocol is not None:
        issues += [
            Issue(i.path, i.message, locator.line(i.path))
            for i in cross_check(protocol, base_dir=base_dir, available=available)
        ]
    return protocol, issues, locator, available == set(Protocol.model_fields)


def _more_issues(
    checks: FileChecks, protocol: Protocol, base_dir: Path, found: list[Issue], locator: Locator
) -> list[Issue]:
    """``checks``' problems at keys not reported already (a missing file found by the
    protocol's own checks is not said again by the check that reads it). With problems
    found already, should the checks fail on a protocol that is inconsistent in another way,
    one line says the files were not all checked (without them, the checks' error stands)."""
    try:
        more = list(checks(protocol, base_dir))
    except Exception:
        if not found:
            raise
        return [Issue((), "the files the protocol names were not all read: correct the "
                      "problems above, then validate again")]  # fmt: skip
    known = {i.path for i in found}
    return [Issue(i.path, i.message, locator.line(i.path)) for i in more if i.path not in known]


def _partial(data: dict[str, Any], sections: set[str]) -> Protocol | None:
    """A protocol holding only the sections that validated (for the checks across sections);
    None if even those do not validate on their own."""
    fields = {
        name: (info.annotation, info)
        for name, info in Protocol.model_fields.items()
        if name in sections
    }
    model = _partial_model(tuple(sorted(fields)))
    try:
        part = model.model_validate({k: v for k, v in data.items() if k in sections})
    except ValidationError:
        return None
    return Protocol.model_construct(**dict(part))


@cache
def _partial_model(names: tuple[str, ...]) -> type[BaseModel]:
    fields: dict[str, Any] = {
        name: (info.annotation, info)
        for name, info in Protocol.model_fields.items()
        if name in names
    }
    return create_model("ProtocolSections", __config__=Protocol.model_config, **fields)


#: what a value of each constrained string is, in words (instead of its regular expression)
_PATTERN_WORDS = {
    VOWELS_PATTERN: "the vowels spoken, in order, as lower-case a i u e o (e.g. aiueo)",
    LANG_PATTERN: "a language code such as ja, en or pt-BR",
}


def _issue_from_pydantic(err: Any, locator: Locator) -> Issue:
    path = clean_loc(err["loc"])
    kind = err["type"]
    if "[key]" in path:
        path = path[: path.index("[key]")]
        if err.get("ctx", {}).get("pattern") == ID_PATTERN:  # a mapping keyed by ids
            return Issue(
                path,
                f"{path[-1]!r} is not a valid id (a letter, then letters, digits, - or single "
                "_): the keys here name conditions, labels or series",
                locator.key_line(path),
            )
        return Issue(
            path,
            f"{path[-1]!r} is not a language code (expected e.g. ja, en); "
            "quote texts that contain commas or colons",
            locator.key_line(path),
        )
    if kind == "extra_forbidden":
        allowed = _allowed_keys(path[:-1])
        hint = f"; allowed keys here: {', '.join(allowed)}" if allowed else ""
        return Issue(path, f"unknown key{hint}", locator.key_line(path))
    if kind == "missing":
        return Issue(path, "required key is missing", locator.key_line(path[:-1]))
    if kind == "string_pattern_mismatch" and err.get("ctx", {}).get("pattern") == ID_PATTERN:
        return Issue(
            path,
            f"{describe(err.get('input'))} is not a valid id: a letter, then letters, digits, "
            "- or single _ (no '__': it separates set, stimulus and condition in clip file names)",
            locator.line(path),
        )
    pattern = err.get("ctx", {}).get("pattern")
    if kind == "string_pattern_mismatch" and pattern in _PATTERN_WORDS:
        return Issue(path, f"{describe(err.get('input'))}: expected {_PATTERN_WORDS[pattern]}",
                     locator.line(path))  # fmt: skip
    if kind == "string_too_long" and path and path[-1] == "id":
        return Issue(path, "ids have at most 64 characters", locator.line(path))
    return Issue(path, pydantic_message(err), locator.line(path))


def _allowed_keys(path: tuple[str | int, ...]) -> list[str]:
    """Field names of the model found at ``path`` inside :class:`Protocol`, if any."""
    model: Any = Protocol
    for part in path:
        if isinstance(part, int):
            continue
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        model = _unwrap(field.annotation)
    return list(getattr(model, "model_fields", {}))


def _unwrap(annotation: Any) -> Any:
    while get_origin(annotation) is not None:
        args = [a for a in get_args(annotation) if a is not type(None)]
        if not args:
            return annotation
        annotation = args[0]
    return annotation
