"""The avatar type: a triangle mesh with blendshape (morph) targets and landmarks.

Contract (DESIGN.md): an :class:`Avatar` has ``neutral`` (V, 3) float32 metres, ``faces``
(F, 3) int32, ``targets`` {name: (V, 3) float32 displacement at full activation},
``landmarks`` {name: vertex index} with at least ``upper_lip``, ``lower_lip``,
``mouth_left``, ``mouth_right`` (inner lip contour), and ``deform(weights) -> (V, 3)``.
Axes: x to the avatar's left, y up, z forward (towards the viewer); metres.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from facelab.errors import AvatarError

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

    def __post_init__(self) -> None:
        self.neutral = np.ascontiguousarray(self.neutral, dtype=np.float32)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        n = len(self.neutral)
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

    def weight_vector(self, weights: Mapping[str, float]) -> np.ndarray:
        """(K,) weights in :attr:`target_names` order; unknown names raise."""
        out = np.zeros(len(self._names), dtype=np.float32)
        index = {n: i for i, n in enumerate(self._names)}
        for name, value in weights.items():
            if name not in index:
                raise AvatarError(f"avatar {self.name!r} has no target {name!r}")
            out[index[name]] = value
        return out

    def deform(self, weights: Mapping[str, float] | np.ndarray) -> np.ndarray:
        """Vertices (V, 3) = neutral + sum_k w_k * target_k (``weights`` by name, or (K,))."""
        w = (
            self.weight_vector(weights)
            if isinstance(weights, Mapping)
            else np.asarray(weights, np.float32)
        )
        active = np.nonzero(w)[0]
        if active.size == 0:
            return self.neutral.copy()
        return self.neutral + (w[active] @ self._stack[active]).reshape(-1, 3)

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
        return h.hexdigest()


def lip_metrics(avatar: Avatar, vertices: np.ndarray) -> dict[str, float]:
    """Inner lip aperture (upper - lower lip, y) and mouth width (left - right corner, x), m."""
    lm = avatar.landmarks
    return {
        "aperture": float(vertices[lm["upper_lip"], 1] - vertices[lm["lower_lip"], 1]),
        "width": float(vertices[lm["mouth_left"], 0] - vertices[lm["mouth_right"], 0]),
        "protrusion": float(0.5 * (vertices[lm["upper_lip"], 2] + vertices[lm["lower_lip"], 2])),
    }
