"""Landmarks that survive vertex reordering: stored as geometry, found again by geometry.

A landmark is a vertex index in memory, but an index means nothing once a tool rewrites the
file: ``gltf-transform meshopt`` reorders vertices for cache locality, quantization moves them
by a fraction of a millimetre, a re-export may weld or split seams. facelab therefore writes,
beside each stored index, the landmark's **rest position** and its **signature** - how the
vertex moves under every target it moves under (``extras.facelab.landmark_points``). Reading
a file, each landmark is the vertex near the stored position (within
:data:`SEARCH_RADIUS_M`) whose position and motion under all targets best match; the stored
index only wins a tie. Two vertices at one place (the closed lips' upper and lower edge) are
told apart by their motion (``jawOpen`` moves only the lower one).

Pure numpy; :mod:`.gltf` calls :func:`landmark_points` when writing and
:func:`resolve_landmarks` when reading.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["SEARCH_RADIUS_M", "landmark_points", "resolve_landmarks"]

#: how far (m) from its stored rest position a landmark is looked for: quantization moves a
#: vertex by well under this (14-bit positions of a 2 m model: 0.12 mm)
SEARCH_RADIUS_M = 0.002
#: a target counts in a signature when it moves the vertex by more than this (m)
_MOVES_M = 1e-6


def landmark_points(
    *, neutral: np.ndarray, targets: Mapping[str, np.ndarray], landmarks: Mapping[str, int]
) -> dict[str, dict[str, Any]]:
    """{landmark: {"position": [x, y, z] (m), "moves": {target: [dx, dy, dz] (m)}}} for every
    landmark: its rest position and its displacement under each target that moves it."""
    out = {}
    for name, index in landmarks.items():
        moves = {
            t: [round(float(v), 7) for v in delta[index]]
            for t, delta in targets.items()
            if float(np.abs(delta[index]).max()) > _MOVES_M
        }
        out[name] = {
            "position": [round(float(v), 7) for v in neutral[index]],
            "moves": moves,
        }
    return out


def resolve_landmarks(
    *,
    points: Mapping[str, Any],
    indices: Mapping[str, int],
    neutral: np.ndarray,
    targets: Mapping[str, np.ndarray],
) -> tuple[dict[str, int], list[str]]:
    """(landmarks, notes): each landmark of ``points`` (see :func:`landmark_points`) found in
    ``neutral`` (V, 3) m and ``targets`` {name: (V, 3) m}; a landmark with no stored point
    keeps its index from ``indices``. ``notes`` say which landmarks were found at another
    index than stored (the file was reordered) or not found at all (dropped)."""
    found: dict[str, int] = {}
    moved, lost = [], []
    for name, index in indices.items():
        point = points.get(name) if isinstance(points, Mapping) else None
        if not isinstance(point, Mapping) or "position" not in point:
            if 0 <= index < len(neutral):
                found[name] = int(index)
            continue
        best = _best_vertex(point, index, neutral=neutral, targets=targets)
        if best is None:
            lost.append(name)
            continue
        found[name] = best
        if best != index:
            moved.append(name)
    notes = []
    if moved:
        notes.append(
            f"landmarks found by geometry at other vertices than stored (the file's vertices "
            f"were reordered): {', '.join(sorted(moved))}"
        )
    if lost:
        notes.append(
            f"landmarks not found within {SEARCH_RADIUS_M * 1e3:g} mm of their stored place "
            f"(dropped): {', '.join(sorted(lost))}"
        )
    return found, notes


def _best_vertex(
    point: Mapping[str, Any],
    index: int,
    *,
    neutral: np.ndarray,
    targets: Mapping[str, np.ndarray],
) -> int | None:
    """The vertex whose rest position and motion best match ``point``; None when no vertex
    lies within :data:`SEARCH_RADIUS_M`."""
    p = np.asarray(point["position"], float)
    dist = np.linalg.norm(neutral.astype(float) - p, axis=1)
    near = np.nonzero(dist <= SEARCH_RADIUS_M)[0]
    if len(near) == 0:
        return None
    moves = point.get("moves") or {}
    cost = dist[near].copy()
    for name, delta in targets.items():
        want = np.asarray(moves.get(name, (0.0, 0.0, 0.0)), float)
        cost += np.linalg.norm(delta[near].astype(float) - want, axis=1)
    for name, want in moves.items():  # a target the file lost: its motion is missing
        if name not in targets:
            cost += float(np.linalg.norm(np.asarray(want, float)))
    best = float(cost.min())
    ties = near[cost <= best + 1e-9]
    return int(index) if index in ties else int(ties[0])
