"""Reading protocol YAML safely, and mapping key paths back to line numbers.

:func:`read_yaml` parses a document once (libyaml's C parser when PyYAML has it) and refuses,
before anything is expanded, what could hang or crash a reader:

* more than :data:`MAX_DEPTH` nested levels (Python's recursive composer would overflow);
* more than :data:`MAX_ALIASES` aliases, or aliases that expand to more than
  :data:`MAX_EXPANDED` values (the "billion laughs" alias bomb: a few lines that expand to
  billions of values);
* files larger than :data:`MAX_BYTES`.

:class:`Locator` walks the composed node tree: it gives the 1-based line of any key path
(for error messages) and finds keys given twice in one mapping, which YAML loaders otherwise
accept silently (the last value wins). It visits every node once, however often aliases
refer to it.
"""

from __future__ import annotations

import contextlib
import gc
import json
from collections.abc import Iterable, Iterator
from typing import Any

import yaml

from facelab.errors import Issue

__all__ = [
    "MAX_ALIASES",
    "MAX_BYTES",
    "MAX_DEPTH",
    "MAX_EXPANDED",
    "Locator",
    "YamlRefusedError",
    "gc_paused",
    "read_data",
    "read_yaml",
]

MAX_BYTES = 50 * 2**20
MAX_DEPTH = 64
MAX_ALIASES = 1_000
MAX_EXPANDED = 5_000_000

_Loader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class YamlRefusedError(Exception):
    """The document is refused before composing it; ``issue`` says why and where."""

    def __init__(self, issue: Issue):
        super().__init__(issue.message)
        self.issue = issue


def _too_deep(line: int | None) -> YamlRefusedError:
    return YamlRefusedError(
        Issue((), f"nested more than {MAX_DEPTH} levels deep; a protocol needs far fewer", line)
    )


def _deep_refused(events: Iterable[yaml.Event]) -> Iterator[yaml.Event]:
    """``events`` as they come, refused past :data:`MAX_DEPTH` open collections. libyaml
    (PyYAML >= 6.0.4) stops at 1,000 levels in its scanner, which reads ahead of the events:
    that error is the same refusal."""
    depth = 0
    try:
        for event in events:
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_DEPTH:
                    raise _too_deep(event.start_mark.line + 1)
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
            yield event
    except yaml.MarkedYAMLError as exc:
        if "nesting depth" not in str(exc.problem):
            raise
        mark = exc.problem_mark
        raise _too_deep(mark.line + 1 if mark is not None else None) from None


def _scan(text: str) -> int:
    """Depth and alias limits from the event stream (constant stack, nothing expanded);
    returns the number of aliases."""
    aliases = 0
    for event in _deep_refused(yaml.parse(text, Loader=_Loader)):
        if isinstance(event, yaml.AliasEvent):
            aliases += 1
            if aliases > MAX_ALIASES:
                raise YamlRefusedError(
                    Issue(
                        (),
                        f"more than {MAX_ALIASES} YAML aliases (*name); refused before expanding "
                        "them",
                        event.start_mark.line + 1,
                    )
                )
    return aliases


def _expanded_size(root: yaml.Node) -> int:
    """How many values the document has once every alias is expanded (memoised per node)."""
    sizes: dict[int, int] = {}
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        if id(node) in sizes:
            continue
        if isinstance(node, yaml.ScalarNode):
            sizes[id(node)] = 1
            continue
        children = (
            [n for pair in node.value for n in pair]
            if isinstance(node, yaml.MappingNode)
            else list(node.value)
        )
        if children_done:
            sizes[id(node)] = 1 + sum(sizes[id(c)] for c in children)
            if sizes[id(node)] > MAX_EXPANDED:
                return sizes[id(node)]
        else:
            stack.append((node, True))
            stack += [(c, False) for c in children if id(c) not in sizes]
    return sizes[id(root)]


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Pause the cyclic garbage collector while building many small objects.

    Composing a large protocol creates millions of nodes; the collector would rescan them
    again and again (4x slower on a 150,000-stimulus file). Nothing here makes cycles."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def read_yaml(text: str) -> tuple[yaml.Node | None, Any]:
    """(node tree, data) of one YAML document, parsed once; raises :class:`YamlRefusedError`
    for documents over the limits and ``yaml.YAMLError`` for invalid YAML."""
    if len(text) > MAX_BYTES:
        raise YamlRefusedError(Issue((), f"the file is larger than {MAX_BYTES // 2**20} MB"))
    aliases = _scan(text)
    loader = _Loader(text)
    with gc_paused():
        return _compose(loader, check_expansion=aliases > 0)


def read_data(text: str, *, json_too: bool = False) -> Any:
    """The data of a YAML (or, with ``json_too``, JSON) document read the way protocols are:
    libyaml's parser where installed (PyYAML's pure-Python one rejects some valid flow
    mappings, e.g. ``{en: Why?}``) and the same limits on size, depth and aliases. Raises
    ``ValueError`` (with the reason) for any document it cannot read."""
    if json_too:
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"not valid JSON: {exc}") from None
    try:
        return read_yaml(text)[1]
    except YamlRefusedError as exc:
        raise ValueError(str(exc)) from None
    except yaml.YAMLError as exc:
        raise ValueError(f"not valid YAML: {exc}") from None


def _compose(loader: Any, *, check_expansion: bool) -> tuple[yaml.Node | None, Any]:
    try:
        root = loader.get_single_node()
        if root is None:
            return None, None
        if check_expansion and _expanded_size(root) > MAX_EXPANDED:
            raise YamlRefusedError(
                Issue(
                    (),
                    f"aliases expand the document to more than {MAX_EXPANDED:,} values "
                    "(an alias bomb?); refused",
                )
            )
        data = loader.construct_document(root)
    finally:
        loader.dispose()
    return root, data


class Locator:
    """Maps key paths to 1-based line numbers using the composed YAML node tree."""

    def __init__(self, root: yaml.Node):
        self.root = root

    def node(self, path: Iterable[str | int]) -> tuple[yaml.Node, bool]:
        """The deepest node along ``path`` and whether the whole path was found."""
        node = self.root
        for part in path:
            child = None
            if isinstance(node, yaml.MappingNode):
                for key, value in node.value:
                    if key.value == str(part):
                        child = value
                        break
            elif (
                isinstance(node, yaml.SequenceNode)
                and isinstance(part, int)
                and 0 <= part < len(node.value)
            ):
                child = node.value[part]
            if child is None:
                return node, False
            node = child
        return node, True

    def key_line(self, path: tuple[str | int, ...]) -> int | None:
        """Line of the *key* that ends ``path`` (for unknown keys), else of the value."""
        if path and isinstance(path[-1], str):
            parent, found = self.node(path[:-1])
            if found and isinstance(parent, yaml.MappingNode):
                for key, _ in parent.value:
                    if key.value == path[-1]:
                        return key.start_mark.line + 1
        return self.line(path)

    def line(self, path: tuple[str | int, ...]) -> int | None:
        node, _ = self.node(path)
        return node.start_mark.line + 1

    def duplicate_keys(self) -> Iterator[Issue]:
        """Keys given twice in one mapping; each node is visited once (aliases share nodes)."""
        seen_nodes: set[int] = set()
        stack: list[tuple[yaml.Node, tuple[str | int, ...]]] = [(self.root, ())]
        found: list[Issue] = []
        while stack:
            node, path = stack.pop()
            if id(node) in seen_nodes:
                continue
            seen_nodes.add(id(node))
            if isinstance(node, yaml.MappingNode):
                seen: dict[str, int] = {}
                for key, value in node.value:
                    name = str(key.value)
                    if name in seen:
                        found.append(
                            Issue(
                                (*path, name),
                                f"duplicate key (first given on line {seen[name]}); give it once",
                                key.start_mark.line + 1,
                            )
                        )
                    seen.setdefault(name, key.start_mark.line + 1)
                    stack.append((value, (*path, name)))
            elif isinstance(node, yaml.SequenceNode):
                stack += [(item, (*path, i)) for i, item in enumerate(node.value)]
        yield from sorted(found, key=lambda i: i.line or 0)
