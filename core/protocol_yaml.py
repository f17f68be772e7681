"""Reading protocol YAML safely, and mapping key paths back to line numbers.

:class:`Locator` walks the composed node tree of a document: it gives the 1-based line of
any key path (for error messages) and finds keys given twice in one mapping, which YAML
loaders otherwise accept silently (the last value wins).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import yaml

from facelab.errors import Issue

__all__ = ["Locator"]


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
        def walk(node: yaml.Node, path: tuple[str | int, ...]) -> Iterator[Issue]:
            if isinstance(node, yaml.MappingNode):
                seen: dict[str, int] = {}
                for key, value in node.value:
                    name = str(key.value)
                    if name in seen:
                        yield Issue(
                            (*path, name),
                            f"duplicate key (first given on line {seen[name]}); give it once",
                            key.start_mark.line + 1,
                        )
                    seen.setdefault(name, key.start_mark.line + 1)
                    yield from walk(value, (*path, name))
            elif isinstance(node, yaml.SequenceNode):
                for i, item in enumerate(node.value):
                    yield from walk(item, (*path, i))

        yield from walk(self.root, ())
