"""Plugins from installed packages: the entry-point groups facelab reads.

A package adds an animation method by naming a :class:`facelab.stimuli.methods.Method`
subclass under the entry-point group ``facelab.methods`` (``pyproject.toml``:
``[project.entry-points."facelab.methods"] jaw_only = "my_package.methods:JawOnly"``) and a
screen kind by naming a :class:`facelab.experiment.screen_kinds.AddedScreen` (or
``ButtonScreen``) subclass under ``facelab.screens``. Nothing in facelab is edited and no
private name is imported.

Loading is lazy (the first time a name facelab does not know is asked for, or ``facelab
plugins``) and guarded: a plugin that cannot be imported, or names something of the wrong
kind, is recorded with a sentence saying which package and what went wrong, and the rest of
facelab goes on working: every command sees only the entries that are ok. A screen kind's
shape is checked here too (its class, name, placement and, unless it is a kind of buttons,
its jsPsych plugin file), so a kind ``facelab plugins`` calls broken is never used. Standard
library only.
"""

from __future__ import annotations

import importlib.metadata as metadata
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["GROUPS", "SCREEN_PLACEMENTS", "PluginEntry", "loaded", "plugin_entries", "screen_kinds"]

#: facelab's entry-point groups, by what they add
GROUPS = {"methods": "facelab.methods", "screens": "facelab.screens"}
#: where an added screen kind may go in a trial
SCREEN_PLACEMENTS = ("after_responses", "after_clip")
_KINDS = "facelab.experiment.screen_kinds."


@dataclass
class PluginEntry:
    """One entry point: its group and name, what it names (``module:attr``), the package that
    declares it (name and version), the object loaded (None when it failed) and, when it
    failed, why (one sentence)."""

    group: str
    name: str
    value: str
    package: str
    version: str
    obj: Any = None
    problem: str | None = None

    def describe(self) -> str:
        state = "ok" if self.problem is None else f"BROKEN: {self.problem}"
        return f"{self.name:<18} {self.package} {self.version} ({self.value}) - {state}"


_CACHE: dict[str, list[PluginEntry]] = {}


def _why(exc: BaseException) -> str:
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        return f"its code needs the module {exc.name!r}, which is not installed"
    if isinstance(exc, ImportError):
        return "its module could not be imported"
    if isinstance(exc, AttributeError):
        return "the module has no object of that name"
    if isinstance(exc, SyntaxError):
        return f"its code has a syntax error (line {exc.lineno})"
    return "importing it raised an error"


def plugin_entries(group: str) -> list[PluginEntry]:
    """Every entry point of ``group`` (a value of :data:`GROUPS`), loaded once (cached);
    failures are recorded in the entries, never raised."""
    if group in _CACHE:
        return _CACHE[group]
    entries = []
    for ep in sorted(metadata.entry_points(group=group), key=lambda e: e.name):
        dist = getattr(ep, "dist", None)
        entry = PluginEntry(group, ep.name, ep.value,
                            dist.metadata["Name"] if dist is not None else "?",
                            dist.version if dist is not None else "?")  # fmt: skip
        where = f"plugin {ep.name!r} from package {entry.package!r} ({ep.value})"
        try:
            entry.obj = ep.load()
        except Exception as exc:
            entry.problem = f"{where} could not be loaded: {_why(exc)}"
        else:
            if group == GROUPS["screens"]:
                problem = _screen_kind_problem(entry.obj, ep.name)
                entry.problem = None if problem is None else f"{where} {problem}"
        entries.append(entry)
    _CACHE[group] = entries
    return entries


def _screen_kind_problem(obj: Any, name: str) -> str | None:
    """What keeps ``obj`` from being the screen kind ``name`` (None: nothing)."""
    bases = {f"{c.__module__}.{c.__qualname__}" for c in getattr(obj, "__mro__", ())}
    if _KINDS + "AddedScreen" not in bases:
        return ("is not a facelab screen kind (a subclass of "
                "facelab.experiment.screen_kinds.AddedScreen or ButtonScreen)")  # fmt: skip
    if obj.kind != name:
        return f"is named {name!r} but its kind is {obj.kind!r}"
    if obj.placement not in SCREEN_PLACEMENTS:
        return f"has placement {obj.placement!r}; expected {', '.join(SCREEN_PLACEMENTS)}"
    if _KINDS + "ButtonScreen" not in bases:  # a kind that draws itself brings its plugin
        js = getattr(obj, "plugin_js", None)
        if js is None:
            return ("names no jsPsych plugin (plugin_js: a .js file in the package) - a kind "
                    "that is not a ButtonScreen draws itself in the browser")  # fmt: skip
        if not Path(js).is_file():
            return (f"names the jsPsych plugin {js}, which is not installed (ship it as "
                    "package data: [tool.setuptools.package-data])")  # fmt: skip
    return None


def loaded(group: str) -> list[PluginEntry]:
    """The entries of ``group`` that loaded."""
    return [e for e in plugin_entries(group) if e.problem is None]


def screen_kinds() -> dict[str, Any]:
    """{kind: class} of the installed screen kinds (entry points ``facelab.screens``) that
    load (the broken ones are named by ``facelab plugins`` and the protocol checks)."""
    return {e.name: e.obj for e in loaded(GROUPS["screens"])}
