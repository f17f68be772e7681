"""Avatars: the public entry points (DESIGN.md's contract) in one place.

* :class:`Avatar` - the mesh type (:mod:`facelab.stimuli.mesh`);
* :func:`default_head` - the built-in head (:mod:`facelab.stimuli.default_head`);
* :func:`load` / :func:`save` - glTF 2.0 files (:mod:`facelab.stimuli.gltf_io`);
* :func:`required_targets`, :func:`check_targets`, :func:`with_viseme_mixes` - what each
  animation method needs from an avatar (:mod:`facelab.stimuli.targets`).
"""

from __future__ import annotations

from pathlib import Path

from facelab.errors import AvatarError
from facelab.stimuli.default_head import default_head
from facelab.stimuli.gltf_io import read_gltf, write_gltf
from facelab.stimuli.mesh import LANDMARKS, Avatar, lip_metrics
from facelab.stimuli.targets import (
    VISEME_MIXES,
    check_targets,
    required_targets,
    with_viseme_mixes,
)

__all__ = [
    "LANDMARKS",
    "VISEME_MIXES",
    "Avatar",
    "AvatarError",
    "check_targets",
    "default_head",
    "lip_metrics",
    "load",
    "required_targets",
    "save",
    "with_viseme_mixes",
]


def load(path: Path | str) -> Avatar:
    """An avatar from a glTF 2.0 file (.gltf or .glb) with morph targets."""
    return read_gltf(Path(path))


def save(avatar: Avatar, path: Path | str) -> None:
    """Write ``avatar`` as glTF 2.0 (.glb binary or .gltf with an embedded buffer)."""
    write_gltf(avatar, Path(path))
