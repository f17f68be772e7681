"""Seeded random mutation of parsed documents (JSON/YAML trees), for the tests that feed
damaged user files to facelab's readers and require a named error or a sound result."""

from __future__ import annotations

import copy
import random
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any


def key_paths(node: Any, prefix: tuple = ()) -> Iterator[tuple]:
    """Every key path below ``node`` (dict keys and list indices), parents first."""
    yield prefix
    if isinstance(node, dict | list):
        for k, v in node.items() if isinstance(node, dict) else enumerate(node):
            yield from key_paths(v, (*prefix, k))


def mutated(
    doc: Any, *, rng: random.Random, values: Sequence[Any], edits: tuple[int, int] = (1, 2)
) -> Any:
    """A deep copy of ``doc`` with ``edits`` (min, max) random edits: a key or list entry
    deleted (30 %) or its value replaced by one of ``values``."""
    doc = copy.deepcopy(doc)
    for _ in range(rng.randint(*edits)):
        where = rng.choice([p for p in key_paths(doc) if p])
        parent = doc
        for k in where[:-1]:
            parent = parent[k]
        if rng.random() < 0.3:
            del parent[where[-1]]
        else:
            parent[where[-1]] = rng.choice(values)
    return doc


def load_or_refuse(path: Path, outcomes: dict[str, int], *, what: str = "") -> None:
    """Load a (damaged) avatar file: it is refused with AvatarError, or it loads into a sound
    avatar (finite vertices and targets, faces within the vertices); count which in
    ``outcomes`` ("loaded", "refused"). Any other exception fails the calling test."""
    import numpy as np

    from facelab.errors import AvatarError
    from facelab.stimuli.avatar import load

    try:
        avatar = load(path)
    except AvatarError:
        outcomes["refused"] += 1
        return
    outcomes["loaded"] += 1
    assert np.isfinite(avatar.neutral).all(), what
    assert avatar.faces.max() < len(avatar.neutral), what
    assert all(np.isfinite(t).all() for t in avatar.targets.values()), what
