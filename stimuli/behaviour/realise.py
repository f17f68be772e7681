"""Behaviour plans made visible: events -> per-frame channel curves added to speech.

Each event contributes amplitude × curve(phase) to its channels over [start, end]
(:func:`curve_values`: smoothstep between the unit's keys). ARKit channels add to the speech
animation's weights and are clamped to [0, 1]; every clamped (frame, channel) is counted in
the report. Speech articulation channels (``jaw* tongue* mouth*`` but the corners) are never
written - the library refuses them. Rotations become a :class:`~facelab.stimuli.avatar.rig.HeadPose`
per frame: yaw/pitch/roll = neck_* + head_* (the rig splits them between neck and head),
eye_* are shown as the avatar's gaze map says (:func:`~facelab.stimuli.avatar.gaze.gaze_map`:
the file's VRM lookAt, eye joints scaled to keep the iris in the eye, or the ``eyeLook*``
shapes). What an avatar cannot show (no head joint, a
missing target) is dropped and named in the report, never silently.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from facelab.stimuli.avatar.gaze import GazeMap, gaze_map
from facelab.stimuli.avatar.lids import LidModel, close_lids, lid_model
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.rig import HeadPose, gaze_weights
from facelab.stimuli.behaviour.library import ROTATIONS, Curve, Library
from facelab.stimuli.behaviour.plan import Plan

__all__ = ["BehaviourFrames", "apply_to_weights", "avatar_traits", "curve_values", "realise"]


def curve_values(curve: Curve, phase: np.ndarray) -> np.ndarray:
    """Curve value at phases (n,) in [0, 1]: smoothstep between successive keys."""
    keys = np.asarray(curve.keys, float)
    p = np.clip(phase, 0.0, 1.0)
    idx = np.clip(np.searchsorted(keys[:, 0], p, side="right") - 1, 0, len(keys) - 2)
    p0, p1 = keys[idx, 0], keys[idx + 1, 0]
    v0, v1 = keys[idx, 1], keys[idx + 1, 1]
    u = np.clip((p - p0) / np.maximum(p1 - p0, 1e-9), 0, 1)
    s = u * u * (3 - 2 * u)
    return v0 + (v1 - v0) * s


@dataclass
class BehaviourFrames:
    """Per-frame behaviour: ``arkit`` {name: (n,) weight offsets}, ``rotations`` (n, 8) degrees
    in :data:`ROTATIONS` order, frame ``times`` (n,) s."""

    times: np.ndarray
    arkit: dict[str, np.ndarray]
    rotations: np.ndarray
    report: dict = field(default_factory=dict)

    def energy(self) -> dict[str, float]:
        """Motion energy: mean |Δ| per second of the ARKit offsets and of the rotations (°/s)
        - a stillness summary for matched-motion controls."""
        if len(self.times) < 2:
            return {"face_per_s": 0.0, "rotation_deg_per_s": 0.0}
        dt = float(self.times[1] - self.times[0])
        face = sum(float(np.abs(np.diff(v)).sum()) for v in self.arkit.values())
        rot = float(np.abs(np.diff(self.rotations, axis=0)).sum())
        span = dt * (len(self.times) - 1)
        return {"face_per_s": face / span, "rotation_deg_per_s": rot / span}


def realise(plan: Plan, library: Library, *, fps: int, n_frames: int) -> BehaviourFrames:
    """The plan's curves at frames k / fps, k < n_frames (clip seconds)."""
    times = np.arange(n_frames) / fps
    arkit: dict[str, np.ndarray] = {}
    rot = np.zeros((n_frames, len(ROTATIONS)))
    units = {u.behaviour: u for u in library.units}
    missing = sorted({e.unit for e in plan.events if e.unit not in units})
    for e in plan.events:
        unit = units.get(e.unit)
        if unit is None or unit.curve is None:
            continue
        a = int(np.floor(e.start_s * fps))
        b = min(n_frames, int(np.ceil(e.end_s * fps)) + 1)
        if b <= a:
            continue
        phase = (times[a:b] - e.start_s) / max(e.end_s - e.start_s, 1e-9)
        shape = np.where((phase >= 0) & (phase <= 1), curve_values(unit.curve, phase), 0.0)
        for ch, amp in e.channels.items():
            if ch in ROTATIONS:
                rot[a:b, ROTATIONS.index(ch)] += amp * shape
            else:
                arkit.setdefault(ch, np.zeros(n_frames))[a:b] += amp * shape
    report = {"units_missing_from_library": missing} if missing else {}
    return BehaviourFrames(times, arkit, rot, report)


def avatar_traits(avatar: Avatar) -> dict:
    """What :func:`apply_to_weights` needs to know of ``avatar``: its target order, whether
    it turns its head and eyes by joints, and its lid limits."""
    roles = set(avatar.skeleton.roles) if avatar.skeleton is not None else set()
    return {
        "target_names": avatar.target_names,
        "has_head": bool({"head", "neck"} & roles),
        "has_eyes": {"eye_left", "eye_right"} <= roles,
        "lids": lid_model(avatar),
        "gaze": gaze_map(avatar),
    }


def apply_to_weights(
    frames: BehaviourFrames,
    weights: np.ndarray,
    *,
    target_names: tuple[str, ...],
    has_head: bool,
    has_eyes: bool,
    lids: LidModel | None = None,
    gaze: GazeMap | None = None,
) -> tuple[np.ndarray, list[HeadPose | None], dict]:
    """Speech weights (n, K) in ``target_names`` order + behaviour -> (weights clamped to
    [0, 1], one pose per frame (None at rest), report).

    The avatar's facts (:func:`avatar_traits` gives them). ``lids``
    (:func:`~facelab.stimuli.avatar.lids.lid_model` of the avatar): a blink during
    a squint or a smile closes the eye no further than shut (the blink gives way), instead of
    driving the upper lid through the lower one. ``gaze``
    (:func:`~facelab.stimuli.avatar.gaze.gaze_map` of the avatar): how the planned gaze
    angles are shown - eye joints turned by the map's ranges, or shapes; without it, eye
    joints turn by the planned angle (``has_eyes``) or the ``eyeLook*`` targets play.

    The report has ``clamped`` {channel: frames} (only channels the behaviour touched),
    ``dropped`` {channel: why}, ``lid_limited_frames`` and ``energy``."""
    out = np.array(weights, dtype=np.float32, copy=True)
    index = {n: i for i, n in enumerate(target_names)}
    dropped: dict[str, str] = {}
    touched: set[str] = set()
    arkit = dict(frames.arkit)
    rot = frames.rotations.copy()
    eye_cols = [ROTATIONS.index("eye_yaw"), ROTATIONS.index("eye_pitch")]
    if gaze is not None and np.any(rot[:, eye_cols]):
        planned = rot[:, eye_cols].copy()
        if gaze.mode == "shapes":
            rot[:, eye_cols] = 0.0
            for k in np.nonzero(np.any(planned, axis=1))[0]:
                for name, v in gaze.shape_weights(*planned[k]).items():
                    arkit.setdefault(name, np.zeros(len(frames.times)))[k] += v
        else:
            for k in np.nonzero(np.any(planned, axis=1))[0]:
                rot[k, eye_cols] = gaze.joint_angles(*planned[k])
    elif not has_eyes and np.any(rot[:, eye_cols]):
        for k in range(len(frames.times)):
            if np.any(rot[k, eye_cols]):
                for name, v in gaze_weights(rot[k, eye_cols[0]], rot[k, eye_cols[1]]).items():
                    arkit.setdefault(name, np.zeros(len(frames.times)))[k] += v
        rot[:, eye_cols] = 0.0
        dropped["eye_yaw/eye_pitch"] = "no eye joints: shown with the eyeLook* targets"
    head_cols = [i for i, n in enumerate(ROTATIONS) if not n.startswith("eye")]
    if not has_head and np.any(rot[:, head_cols]):
        rot[:, head_cols] = 0.0
        dropped["neck_*/head_*"] = "the avatar has no head or neck joint: head motion not shown"
    for name, col in arkit.items():
        if name not in index:
            if np.any(col):
                dropped[name] = "the avatar has no such target"
            continue
        out[:, index[name]] += col.astype(np.float32)
        touched.add(name)
    clamped = {}
    for name in sorted(touched):
        j = index[name]
        n = int(np.count_nonzero((out[:, j] > 1) | (out[:, j] < 0)))
        if n:
            clamped[name] = n
    np.clip(out, 0.0, 1.0, out=out)
    out, lid_limited = close_lids(out, lids)
    poses: list[HeadPose | None] = []
    for k in range(len(frames.times)):
        r = rot[k]
        if not np.any(r):
            poses.append(None)
            continue
        poses.append(
            HeadPose(
                yaw=float(r[0] + r[3]),
                pitch=float(r[1] + r[4]),
                roll=float(r[2] + r[5]),
                eye_yaw=float(r[6]),
                eye_pitch=float(r[7]),
            )
        )
    report = {
        "clamped_frames": clamped,
        "dropped": dropped,
        "lid_limited_frames": lid_limited,
        "energy": {k: round(v, 4) for k, v in frames.energy().items()},
        **({"gaze": gaze.describe()} if gaze is not None else {}),
        **frames.report,
    }
    return out, poses, report
