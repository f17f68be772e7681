"""The avatar type: a triangle mesh with blendshape (morph) targets and landmarks.

Contract (DESIGN.md): an :class:`Avatar` has ``neutral`` (V, 3) float32 metres, ``faces``
(F, 3) int32, ``targets`` {name: (V, 3) float32 displacement at full activation},
``landmarks`` {name: vertex index} with at least ``upper_lip``, ``lower_lip``,
``mouth_left``, ``mouth_right`` (inner lip contour), and ``deform(weights) -> (V, 3)``.
Axes: x to the avatar's left, y up, z forward (towards the viewer); metres.

Beyond the contract an avatar may carry a :class:`~facelab.stimuli.avatar.rig.Skeleton` (then
``deform(weights, pose=HeadPose(...))`` turns head, neck and eyes by skinning), texture
coordinates with base-colour textures, a per-vertex gloss (specular strength), and ``source``
facts about the file it came from (its kind - default, gltf, rpm, vrm0, vrm1 - and, for VRM,
which targets stand in for which presets).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from facelab.errors import AvatarError
from facelab.stimuli.avatar.rig import HeadPose, Skeleton, skin

__all__ = ["LANDMARKS", "Avatar", "lip_metrics"]

LANDMARKS = ("upper_lip", "lower_lip", "mouth_left", "mouth_right")


@dataclass
class Avatar:
    neutral: np.ndarray
    faces: np.ndarray
    targets: dict[str, np.ndarray]
    landmarks: dict[str, int]
    colors: np.ndarray | None = None  # (V, 3) base colour in [0, 1], for rendering
    name: str = "avatar"
    parts: dict[str, np.ndarray] = field(default_factory=dict)  # part name -> vertex indices
    skeleton: Skeleton | None = None
    uv: np.ndarray | None = None  # (V, 2) texture coordinates (glTF convention, v down)
    textures: tuple[np.ndarray, ...] = ()  # (H, W, 3) uint8 sRGB; (H, W, 4) lets light through
    face_texture: np.ndarray | None = None  # (F,) index into textures, -1 untextured
    gloss: np.ndarray | None = None  # (V,) specular strength in [0, 1] (None: 1 everywhere)
    source: dict[str, Any] = field(default_factory=dict)  # kind, file, preset stand-ins...

    def __post_init__(self) -> None:
        self.neutral = np.ascontiguousarray(self.neutral, dtype=np.float32)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        n = len(self.neutral)
        if self.skeleton is not None and len(self.skeleton.joints) != n:
            raise AvatarError(
                f"skeleton has weights for {len(self.skeleton.joints)} vertices, expected {n}"
            )
        if self.uv is not None and self.uv.shape != (n, 2):
            raise AvatarError(f"uv has shape {self.uv.shape}, expected ({n}, 2)")
        if self.face_texture is not None and (
            len(self.face_texture) != len(self.faces)
            or (self.face_texture.size and self.face_texture.max() >= len(self.textures))
        ):
            raise AvatarError("face_texture must give one texture index (or -1) per face")
        for name, delta in self.targets.items():
            if delta.shape != (n, 3):
                raise AvatarError(f"target {name!r} has shape {delta.shape}, expected ({n}, 3)")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n):
            raise AvatarError("faces refer to vertices that do not exist")
        self._names = tuple(self.targets)
        self._stack = (
            np.stack([self.targets[k].reshape(-1) for k in self._names]).astype(np.float32)
            if self._names
            else np.zeros((0, n * 3), np.float32)
        )

    @property
    def target_names(self) -> tuple[str, ...]:
        return self._names

    def drawn(self) -> np.ndarray:
        """(V,) bool: the vertices some triangle uses (a surface its material hides keeps
        its vertices, so indices hold, but no triangles: it frames and audits nothing)."""
        mask = np.zeros(len(self.neutral), bool)
        mask[np.asarray(self.faces, np.int64).reshape(-1)] = True
        return mask

    def weight_vector(self, weights: Mapping[str, float]) -> np.ndarray:
        """(K,) weights in :attr:`target_names` order; unknown names raise."""
        out = np.zeros(len(self._names), dtype=np.float32)
        index = {n: i for i, n in enumerate(self._names)}
        for name, value in weights.items():
            if name not in index:
                raise AvatarError(f"avatar {self.name!r} has no target {name!r}")
            out[index[name]] = value
        return out

    def deform(
        self, weights: Mapping[str, float] | np.ndarray, *, pose: HeadPose | None = None
    ) -> np.ndarray:
        """Vertices (V, 3) = skin(neutral + sum_k w_k * target_k, pose) (``weights`` by name,
        or (K,) in :attr:`target_names` order; ``pose`` needs a skeleton)."""
        w = (
            self.weight_vector(weights)
            if isinstance(weights, Mapping)
            else np.asarray(weights, np.float32)
        )
        active = np.nonzero(w)[0]
        if active.size * 4 > len(w):  # many shapes at once (speech): one product, no copies
            verts = self.neutral + (w @ self._stack).reshape(-1, 3)
        elif active.size:
            verts = self.neutral + (w[active] @ self._stack[active]).reshape(-1, 3)
        else:
            verts = self.neutral.copy()
        if pose is None or pose.is_rest():
            return verts
        if self.skeleton is None:
            raise AvatarError(
                f"avatar {self.name!r} has no skeleton: it cannot turn its head or eyes"
            )
        return skin(verts, self.skeleton, pose)

    def replace(self, **changes: Any) -> Avatar:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def content_hash(self) -> str:
        """SHA-256 of the geometry, targets, colours and landmarks (for clip caching)."""
        h = hashlib.sha256()
        for arr in (
            self.neutral,
            self.faces,
            self._stack,
            self.colors if self.colors is not None else np.zeros(0),
        ):
            h.update(np.ascontiguousarray(arr).tobytes())
        h.update(repr(sorted(self.landmarks.items())).encode())
        h.update("|".join(self._names).encode())
        if self.skeleton is not None:
            sk = self.skeleton
            for arr in (sk.parents, sk.pivots, sk.joints, sk.weights):
                h.update(np.ascontiguousarray(arr).tobytes())
            h.update(repr((sk.names, sorted(sk.roles.items()))).encode())
        for arr in (self.uv, self.face_texture, self.gloss, *self.textures):
            if arr is not None:
                h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()


def lip_metrics(avatar: Avatar, vertices: np.ndarray) -> dict[str, float]:
    """Inner lip aperture (upper - lower lip, y) and mouth width (left - right corner, x), m."""
    lm = avatar.landmarks
    return {
        "aperture": float(vertices[lm["upper_lip"], 1] - vertices[lm["lower_lip"], 1]),
        "width": float(vertices[lm["mouth_left"], 0] - vertices[lm["mouth_right"], 0]),
        "protrusion": float(0.5 * (vertices[lm["upper_lip"], 2] + vertices[lm["lower_lip"], 2])),
    }
