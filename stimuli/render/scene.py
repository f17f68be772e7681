"""A protocol's scene: the avatar it draws (:func:`load_avatar`), the render settings
(:func:`settings_for`), where the camera stands and what it aims at (:func:`framing`) and the
lights - pure functions shared by the offline renderer (:mod:`.renderer`) and the live browser
and VR views (``facelab serve`` with ``presentation.display: live3d | webxr``,
:func:`camera_json`), so a live frame and the offline frame of the same instant are framed and
lit alike. No pyrender here."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facelab.protocol import Protocol
from facelab.stimuli.avatar import Avatar, default_head, load, with_viseme_mixes
from facelab.stimuli.avatar.audit import moved_vertices
from facelab.stimuli.methods import check_playable, get

__all__ = [
    "AMBIENT",
    "AMBIENT_UP",
    "DEFAULT_DISTANCE_M",
    "DEFAULT_HEAD_HEIGHT_M",
    "LIGHTS",
    "CameraPlacement",
    "RenderSettings",
    "camera_json",
    "camera_placement",
    "eye_midpoint",
    "face_box",
    "face_closeup",
    "framing",
    "load_avatar",
    "mouth_centre",
    "settings_for",
]


@dataclass(frozen=True)
class RenderSettings:
    """Frame size; the camera (``distance_m`` None frames the head: 0.65 m for a head the size
    of the default one, scaled with the head's height; ``target_m`` None aims at the head's
    centre - found from landmarks, the head joint's vertices or the model's top); background
    colour (linear 0-1) and multisampling."""

    width: int = 1280
    height: int = 720
    distance_m: float | None = None
    fov_deg: float = 30.0
    height_m: float = 0.0
    background: tuple[float, float, float] = (0.5, 0.5, 0.5)
    msaa: int = 1  # protocols default to 4 (smooth, 0.71x real time at 720p30 on 2 cores)
    target_m: tuple[float, float, float] | None = None
    zoom: float = 1.0  # divides the automatic distance (contact sheets come closer; from 1.5
    # on, an avatar without face landmarks is framed on the vertices its shapes move)


#: camera distance for the default head, and that head's height from chin to crown (m)
DEFAULT_DISTANCE_M = 0.65
DEFAULT_HEAD_HEIGHT_M = 0.24


def framing(avatar: Avatar, settings: RenderSettings) -> tuple[np.ndarray, float]:
    """The point the camera aims at and its distance (see :class:`RenderSettings`)."""
    s = settings
    a = avatar
    lm = a.landmarks
    head_height = DEFAULT_HEAD_HEIGHT_M
    if s.target_m is not None:
        centre = np.asarray(s.target_m, float)
    elif "upper_lip" in lm and {"upper_lid_left", "upper_lid_right"} <= set(lm):
        eyes = 0.5 * (a.neutral[lm["upper_lid_left"]] + a.neutral[lm["upper_lid_right"]])
        c = 0.5 * (eyes + a.neutral[lm["upper_lip"]])
        centre = np.array([0.0, c[1] + 0.004, c[2] - 0.02])
        if a.source.get("kind") != "default":
            head_height = 3.2 * float(eyes[1] - a.neutral[lm["upper_lip"], 1])
    else:
        head = _head_vertices(avatar)
        lo, hi = head.min(axis=0), head.max(axis=0)
        centre = np.array(
            [(lo[0] + hi[0]) / 2, lo[1] + 0.52 * (hi[1] - lo[1]), (lo[2] + hi[2]) / 2]
        )
        head_height = float(hi[1] - lo[1])
        face = _face_vertices(avatar) if s.zoom >= 1.5 and s.distance_m is None else None
        if face is not None:  # a close-up without landmarks: frame what the shapes move
            flo, fhi = face.min(axis=0), face.max(axis=0)
            centre = np.array([(flo[0] + fhi[0]) / 2, (flo[1] + fhi[1]) / 2, centre[2]])
            fit = 1.15 * max(fhi[1] - flo[1], (fhi[0] - flo[0]) * s.height / s.width)
            zoomed = DEFAULT_DISTANCE_M * max(head_height, 1e-3) / DEFAULT_HEAD_HEIGHT_M
            return centre, float(
                max(zoomed / s.zoom, fit / (2 * np.tan(np.radians(s.fov_deg) / 2)))
            )
    distance = (
        s.distance_m
        if s.distance_m is not None
        else DEFAULT_DISTANCE_M * max(head_height, 1e-3) / DEFAULT_HEAD_HEIGHT_M / s.zoom
    )
    return centre, float(distance)


def face_box(avatar: Avatar) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (3,) m: the box of the avatar's face at rest, brows to chin. From the eye and
    lip landmarks when the avatar has them (eyes to mouth is 0.53 of the box's height, the
    box as wide as high), else from the vertices its shapes move (mouth, lids, brows), else
    from the head."""
    a = avatar
    lm = a.landmarks
    if "upper_lip" in lm and {"upper_lid_left", "upper_lid_right"} <= set(lm):
        eyes = 0.5 * (a.neutral[lm["upper_lid_left"]] + a.neutral[lm["upper_lid_right"]])
        mouth = a.neutral[lm["upper_lip"]].astype(float)
        d = float(eyes[1] - mouth[1])
        if d > 0:
            centre = np.array([0.5 * (eyes[0] + mouth[0]), 0.5 * (eyes[1] + mouth[1]) - 0.15 * d,
                               max(eyes[2], mouth[2])])  # fmt: skip
            half = 0.95 * d
            return centre - half, centre + half
    face = _face_vertices(a)
    points = face if face is not None else _head_vertices(a)
    return points.min(axis=0).astype(float), points.max(axis=0).astype(float)


def face_closeup(
    avatar: Avatar, *, size_px: int, msaa: int = 4, margin: float = 1.2,
    background: tuple[float, float, float] = (0.5, 0.5, 0.5),
) -> RenderSettings:  # fmt: skip
    """Square ``size_px`` frame settings whose camera fits :func:`face_box` (times
    ``margin``) from straight ahead: what contact sheets show, whatever the avatar's size or
    where its face sits (a full-body VRoid export, a bust, the default head)."""
    lo, hi = face_box(avatar)
    centre = 0.5 * (lo + hi)
    extent = margin * float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-3))
    fov = 30.0
    distance = 0.5 * extent / np.tan(np.radians(fov) / 2) + 0.5 * float(hi[2] - lo[2])
    return RenderSettings(
        width=size_px, height=size_px, fov_deg=fov, msaa=msaa, background=background,
        distance_m=distance, target_m=(float(centre[0]), float(centre[1]), float(centre[2])),
    )  # fmt: skip


def _face_vertices(avatar: Avatar) -> np.ndarray | None:
    """Rest vertices that the avatar's shapes move (the face: mouth, jaw, lids, brows,
    cheeks), or None when fewer than 10 move."""
    moved = moved_vertices(avatar, avatar.targets, at_least=10)
    return avatar.neutral[moved] if moved is not None else None


def _head_vertices(avatar: Avatar) -> np.ndarray:
    """Rest vertices of the head: those skinned to the head joint, else a mesh named like
    a head (``Wolf3D_Head``, ``Face``, ``head``), else the model's top."""
    a = avatar
    drawn = a.drawn()  # a surface its material hides frames nothing
    sk = a.skeleton
    if sk is not None and "head" in sk.roles:
        rows = np.asarray(sk.vertices_of(sk.roles["head"]), np.int64)
        rows = rows[drawn[rows]]
        if len(rows) >= 10:
            return a.neutral[rows]
    named = [
        idx[drawn[idx]]
        for name, idx in a.parts.items()
        if any(key in name.lower() for key in ("head", "face")) and drawn[idx].sum() >= 10
    ]
    if named:
        return a.neutral[np.concatenate(named)]
    shown = a.neutral[drawn]
    lo, hi = shown.min(axis=0), shown.max(axis=0)
    height = hi[1] - lo[1]
    if height > 0.6:  # a full body: its top 0.25 m or so is the head
        return shown[shown[:, 1] > hi[1] - min(0.25, height / 6)]
    return shown


#: The offline lights (direction towards the light in the avatar's world frame, intensity
#: on linear base colours); the hemisphere ambient is 0.20 + 0.07 * normal.y. The renderer
#: shades with these per vertex; the live view gives three.js the same lights.
LIGHTS = (
    ((-0.55, 0.60, 0.60), 0.62),  # key, upper left of the viewer
    ((0.75, 0.15, 0.65), 0.30),  # fill, right
    ((0.0, 0.35, -1.0), 0.16),  # rim from behind
)
#: the hemisphere ambient, AMBIENT + AMBIENT_UP * normal.y (sky above, warm bounce below)
AMBIENT, AMBIENT_UP = 0.20, 0.07


@dataclass(frozen=True)
class CameraPlacement:
    """Where the camera stands (``eye``) and what it aims at (``target``), metres in the
    avatar's world frame, and its near and far planes (m)."""

    eye: np.ndarray
    target: np.ndarray
    near: float
    far: float


def camera_placement(avatar: Avatar, settings: RenderSettings) -> CameraPlacement:
    """The offline renderer's camera (and the live view's): :func:`framing`'s distance in
    front of the aim point, ``height_m`` above it."""
    centre, distance = framing(avatar, settings)
    return CameraPlacement(
        eye=centre + np.array([0.0, settings.height_m, distance]),
        target=centre,
        near=max(0.01, 0.08 * distance),
        far=20.0 * distance,
    )


def camera_json(avatar: Avatar, settings: RenderSettings) -> dict[str, Any]:
    """The offline camera as the live view needs it: eye and target (m, avatar world frame),
    vertical field of view (degrees), near/far planes (m), frame size (px), background
    (linear 0-1, drawn as is by the offline renderer), the lights and the head-centre
    height (the point a VR view places at the protocol's distance)."""
    cam = camera_placement(avatar, settings)
    return {
        "eye": _rounded(cam.eye),
        "target": _rounded(cam.target),
        "fov_deg": settings.fov_deg,
        "near": cam.near,
        "far": cam.far,
        "width": settings.width,
        "height": settings.height,
        "background": list(settings.background),
        "lights": [{"direction": list(d), "intensity": i} for d, i in LIGHTS],
        "ambient": {"sky": AMBIENT + AMBIENT_UP, "ground": AMBIENT - AMBIENT_UP},
        "eyes": _rounded(eye_midpoint(avatar)),
        "mouth": _rounded(mouth_centre(avatar)),
    }


def _rounded(point: np.ndarray | None) -> list[float] | None:
    return None if point is None else [round(float(v), 6) for v in point]


def eye_midpoint(avatar: Avatar) -> np.ndarray | None:
    """(3,) m: between the eyes at rest - the eye joints' pivots when the skeleton has both,
    else the middle of the four eyelid landmarks; None when the avatar has neither (a VR
    view then anchors the aim point instead)."""
    sk = avatar.skeleton
    if sk is not None and {"eye_left", "eye_right"} <= set(sk.roles):
        return 0.5 * (sk.pivots[sk.roles["eye_left"]] + sk.pivots[sk.roles["eye_right"]])
    return _landmark_mean(
        avatar, ("upper_lid_left", "lower_lid_left", "upper_lid_right", "lower_lid_right")
    )


def mouth_centre(avatar: Avatar) -> np.ndarray | None:
    """(3,) m: the middle of the inner lip contour's four landmarks at rest (where a VR view
    puts the voice); None for an avatar without them (a VR view then uses the aim point)."""
    return _landmark_mean(avatar, ("upper_lip", "lower_lip", "mouth_left", "mouth_right"))


def _landmark_mean(avatar: Avatar, names: tuple[str, ...]) -> np.ndarray | None:
    """(3,) m: the mean rest position of landmarks ``names``; None unless it has them all."""
    if not all(k in avatar.landmarks for k in names):
        return None
    return avatar.neutral[[avatar.landmarks[k] for k in names]].astype(float).mean(axis=0)


def load_avatar(protocol: Protocol, *, base_dir: Path) -> Avatar:
    """The protocol's avatar, checked to play every condition's method; with ``viseme_*``
    shapes from ARKit mixes when a method drives visemes the avatar lacks."""
    spec = protocol.rendering.avatar
    avatar = default_head() if spec == "default" else load(base_dir / spec)
    for cond in protocol.conditions:
        check_playable(avatar, cond.method, cond.settings, base_dir=base_dir)
    needs_visemes = any(get(c.method).uses_visemes for c in protocol.conditions)
    return with_viseme_mixes(avatar) if needs_visemes else avatar


def settings_for(protocol: Protocol) -> RenderSettings:
    r = protocol.rendering
    return RenderSettings(
        width=r.width,
        height=r.height,
        distance_m=r.camera.distance_m,
        target_m=tuple(r.camera.target_m) if r.camera.target_m is not None else None,
        fov_deg=r.camera.fov_deg,
        height_m=r.camera.height_m,
        background=tuple(r.background),
        msaa=r.msaa,
    )
