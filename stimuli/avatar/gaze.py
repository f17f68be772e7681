"""How an avatar shows a gaze direction: which parts move (eye joints or shapes) and how far.

The behaviour layer plans gaze in degrees of the eye's line of sight (``eye_yaw`` positive to
the avatar's left, ``eye_pitch`` positive down). An eye joint turned by that angle shows it
only when the joint sits at the eyeball's centre: a VRoid export's eye joints sit 73 mm behind
the iris, so 20 degrees swings the iris out of the eye. :func:`gaze_map` decides, from the file
and then the geometry:

1. the file's **VRM lookAt** (VRM 1.0 ``VRMC_vrm.lookAt``, VRM 0.x ``firstPerson.lookAt*``):
   ``bone`` type turns the eye joints by the file's range maps (input max -> output degrees per
   direction), ``expression``/``BlendShape`` type plays its lookUp/Down/Left/Right presets;
2. else, when the eye joints would swing the iris out of the eye (their pivot measured against
   the eye's front, :func:`safe_eye_angle`) and the avatar has usable ARKit ``eyeLook*`` shapes,
   those shapes (the artist's own gaze; weight 1 taken as :data:`SHAPE_RANGE_DEG`);
3. else the eye joints, scaled down so the largest planned gaze keeps the iris inside;
4. no eye joints: the ``eyeLook*`` shapes.

Pure numpy on the avatar's arrays and ``source`` facts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from facelab.stimuli.avatar.audit import EMPTY_TARGET_MM, target_motion_mm
from facelab.stimuli.avatar.mesh import Avatar

__all__ = [
    "GAZE_RANGE_DEG",
    "SHAPE_RANGE_DEG",
    "GazeMap",
    "gaze_map",
    "safe_eye_angle",
]

#: the largest gaze shift (degrees) the behaviour layer plans
GAZE_RANGE_DEG = 20.0
#: the gaze (degrees) an ARKit eyeLook shape at weight 1 is taken to show
SHAPE_RANGE_DEG = 25.0
_EYE_LOOK = tuple(
    f"eyeLook{d}{s}" for s in ("Left", "Right") for d in ("Out", "In", "Up", "Down")
)


@dataclass(frozen=True)
class GazeMap:
    """``mode`` ``joints`` (turn the eye joints) or ``shapes`` (play targets); ``ranges``
    {direction: (input max deg, output)} for out, in, up, down - output in degrees of joint
    turn (joints) or target weight (shapes); ``targets`` {direction: (left eye's target,
    right eye's target)} for shapes; ``source`` says where the map came from."""

    mode: str
    ranges: dict[str, tuple[float, float]]
    source: str
    targets: dict[str, tuple[str, str]] = field(default_factory=dict)

    def _scale(self, direction: str, angle: float) -> float:
        top, out = self.ranges.get(direction, (GAZE_RANGE_DEG, GAZE_RANGE_DEG))
        return float(out * min(abs(angle), top) / top) if top > 0 else 0.0

    def joint_angles(self, eye_yaw: float, eye_pitch: float) -> tuple[float, float]:
        """(yaw, pitch) degrees to turn both eye joints for a gaze of (``eye_yaw``,
        ``eye_pitch``) degrees (horizontal: the outer range for the eye the gaze moves
        outwards, as VRM averages it; here one turn for both eyes, from the outer map)."""
        yaw = np.sign(eye_yaw) * self._scale("out", eye_yaw)
        pitch = np.sign(eye_pitch) * self._scale("down" if eye_pitch > 0 else "up", eye_pitch)
        return float(yaw), float(pitch)

    def shape_weights(self, eye_yaw: float, eye_pitch: float) -> dict[str, float]:
        """{target: weight} showing the gaze with shapes."""
        out: dict[str, float] = {}
        if eye_yaw:
            left = eye_yaw > 0  # towards the avatar's left: left eye out, right eye in
            for eye, direction in ((0, "out" if left else "in"), (1, "in" if left else "out")):
                name = self.targets.get(direction, ("", ""))[eye]
                if name:  # one shape for both eyes (VRM lookLeft) counts once
                    out[name] = max(out.get(name, 0.0), self._scale(direction, eye_yaw))
        if eye_pitch:
            direction = "down" if eye_pitch > 0 else "up"
            for name in self.targets.get(direction, ("", "")):
                if name:
                    out[name] = max(out.get(name, 0.0), self._scale(direction, eye_pitch))
        return out

    def describe(self) -> str:
        span = ", ".join(f"{d} {a:g}->{o:g}" for d, (a, o) in sorted(self.ranges.items()))
        unit = "deg" if self.mode == "joints" else "weight"
        return f"gaze by {self.mode} ({self.source}; {span} {unit})"


def safe_eye_angle(avatar: Avatar, role: str) -> tuple[float, float, float] | None:
    """(safe angle deg, pivot depth m, eye width m) for the eye joint ``role``: the turn
    that moves the eye's front by a third of the eye's width; None without that joint or
    its vertices."""
    sk = avatar.skeleton
    if sk is None or role not in sk.roles:
        return None
    j = sk.roles[role]
    verts = avatar.neutral[sk.vertices_of(j)].astype(float)
    if len(verts) < 4:
        return None
    depth = float(verts[:, 2].max() - sk.pivots[j][2])
    width = float(np.ptp(verts[:, 0]))
    travel = width / 3.0
    angle = 90.0 if depth <= travel else float(np.degrees(np.arcsin(travel / depth)))
    return angle, depth, width


def _shape_targets(avatar: Avatar) -> dict[str, tuple[str, str]] | None:
    names = [n for n in _EYE_LOOK if n in avatar.targets]
    if len(names) < len(_EYE_LOOK):
        return None
    motion = target_motion_mm(avatar, names)
    if any(motion[n] < EMPTY_TARGET_MM for n in names):
        return None
    return {d.lower(): (f"eyeLook{d}Left", f"eyeLook{d}Right") for d in ("Out", "In", "Up", "Down")}


def _vrm_look_at(avatar: Avatar) -> GazeMap | None:
    look = avatar.source.get("look_at")
    if not isinstance(look, dict) or not look.get("ranges"):
        return None
    ranges = {d: (float(a), float(o)) for d, (a, o) in look["ranges"].items()}
    if look.get("type") == "bone":
        return GazeMap("joints", ranges, "the file's VRM lookAt, bone type")
    # one expression moves both eyes: a gaze to the avatar's left is lookLeft for each eye
    names = {
        "out": ("vrm_lookLeft", "vrm_lookRight"),
        "in": ("vrm_lookRight", "vrm_lookLeft"),
        "up": ("vrm_lookUp", "vrm_lookUp"),
        "down": ("vrm_lookDown", "vrm_lookDown"),
    }
    targets = {d: pair for d, pair in names.items() if all(n in avatar.targets for n in pair)}
    if not targets:
        return None
    return GazeMap("shapes", ranges, "the file's VRM lookAt, expression type", targets)


def gaze_map(avatar: Avatar) -> GazeMap:
    """How ``avatar`` shows gaze (see the module docstring)."""
    vrm = _vrm_look_at(avatar)
    if vrm is not None:
        return vrm
    shapes = _shape_targets(avatar)
    eyes = [safe_eye_angle(avatar, r) for r in ("eye_left", "eye_right")]
    if all(e is not None for e in eyes):
        safe = min(e[0] for e in eyes if e is not None)
        if safe >= GAZE_RANGE_DEG:
            full = {d: (GAZE_RANGE_DEG, GAZE_RANGE_DEG) for d in ("out", "in", "up", "down")}
            return GazeMap("joints", full, "eye joints at the eyeball's centre")
        if shapes is not None:
            ranges = {d: (SHAPE_RANGE_DEG, 1.0) for d in shapes}
            return GazeMap("shapes", ranges, f"eyeLook shapes: the eye joints turn about a point "
                           f"behind the eye (safe to {safe:.1f} deg)", shapes)  # fmt: skip
        scaled = {d: (GAZE_RANGE_DEG, round(safe, 2)) for d in ("out", "in", "up", "down")}
        return GazeMap("joints", scaled, f"eye joints scaled to keep the iris in the eye "
                       f"(safe to {safe:.1f} deg)")  # fmt: skip
    ranges = {d: (SHAPE_RANGE_DEG, 1.0) for d in ("out", "in", "up", "down")}
    targets = shapes or {d.lower(): (f"eyeLook{d}Left", f"eyeLook{d}Right")
                         for d in ("Out", "In", "Up", "Down")}  # fmt: skip
    return GazeMap("shapes", ranges, "no eye joints: eyeLook shapes", targets)
