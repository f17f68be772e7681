"""Avatars: the public entry points (DESIGN.md's contract) in one place.

* :class:`Avatar` - the mesh type (:mod:`facelab.stimuli.avatar.mesh`);
* :func:`default_head` - the built-in head (:mod:`facelab.stimuli.avatar.default_head`);
* :func:`load` / :func:`save` - glTF 2.0 files (:mod:`facelab.stimuli.avatar.gltf`);
* :func:`with_viseme_mixes` - ``viseme_*`` shapes built from ARKit mixes
  (:mod:`facelab.stimuli.avatar.targets`); what each animation method needs from an avatar
  is the method's own (``facelab.stimuli.methods``).

The sub-package also holds the skeleton and skinning (:mod:`.rig`), VRM (:mod:`.vrm`), and the
small sample avatars the tests load (:mod:`.samples`).
"""

from __future__ import annotations

from pathlib import Path

from facelab.errors import AvatarError
from facelab.stimuli.avatar.default_head import default_head
from facelab.stimuli.avatar.gltf import read_gltf, write_gltf
from facelab.stimuli.avatar.mesh import LANDMARKS, Avatar, lip_metrics
from facelab.stimuli.avatar.targets import VISEME_MIXES, with_viseme_mixes

__all__ = [
    "LANDMARKS",
    "VISEME_MIXES",
    "Avatar",
    "AvatarError",
    "default_head",
    "lip_metrics",
    "load",
    "save",
    "with_viseme_mixes",
]


def load(path: Path | str) -> Avatar:
    """An avatar from a glTF 2.0 file (.gltf or .glb) with morph targets."""
    return read_gltf(Path(path))


def save(avatar: Avatar, path: Path | str) -> None:
    """Write ``avatar`` as glTF 2.0 (.glb binary or .gltf with an embedded buffer)."""
    write_gltf(avatar, Path(path))
