"""The avatar audit: what the avatar's geometry can show of what the protocol asks, measured
from the file without rendering (``facelab check``, ``validate`` and ``avatar inspect``).

Rows (check ``avatar_audit``, no clip):

* per condition, every target its method drives on this avatar moves a vertex by
  :data:`~facelab.stimuli.avatar.audit.EMPTY_TARGET_MM` or more at full weight
  (``target_motion_mm:<name>``) and none by more than
  :data:`~facelab.stimuli.avatar.audit.WILD_TARGET_MM` (``target_reach_mm:<name>``, a row
  only for a target that does: shapes at another scale than the mesh tear the face), and no
  two of them are the same shape
  (``identical_driven_targets``); a stand-in (the avatar's own vowel shapes playing Z) is
  reported as it plays;
* the lip landmarks, when the file has them, lie where a mouth is: the upper lip not below the
  lower, the left corner left of the right, a mouth 15-90 mm wide, both lips between the
  corners (``lip_landmarks_consistent``; facelab resolves landmarks from their stored
  positions, so a tool that reorders vertices cannot move them);
* how the avatar shows gaze (``gaze_shown_by``: the file's VRM lookAt, eye joints, or
  eyeLook shapes; :mod:`facelab.stimuli.avatar.gaze`) and, per eye joint, how far behind the
  front of the eye it turns the eye (``eye_pivot_depth_mm``), the turn that keeps the iris
  inside the eye (``gaze_range_deg``: the angle that moves the front of the eye by a third of
  the eye's width) and the turn the largest planned gaze gets (``gaze_played_deg``, at most
  ``gaze_range_deg``); an error when a condition has a behaviour layer (which moves the
  gaze), else a warning.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facelab.protocol import Protocol
from facelab.stimuli.avatar.audit import (
    EMPTY_TARGET_MM,
    WILD_TARGET_MM,
    WILD_TARGET_SPANS,
    face_orientation,
    identical_targets,
    target_motion_mm,
)
from facelab.stimuli.avatar.gaze import GAZE_RANGE_DEG, gaze_map, safe_eye_angle
from facelab.stimuli.avatar.mesh import LANDMARKS, Avatar
from facelab.stimuli.checks.rows import CheckRow, at_least, at_most, info
from facelab.stimuli.methods import get

__all__ = ["GAZE_RANGE_DEG", "audit_avatar", "eye_rows", "landmark_rows", "orientation_rows"]

CHECK = "avatar_audit"


def audit_avatar(avatar: Avatar, protocol: Protocol, *, base_dir: Path) -> list[CheckRow]:
    """Every avatar-audit row for ``protocol``'s conditions on ``avatar``."""
    rows: list[CheckRow] = []
    found = face_orientation(avatar)  # the face's own scale: mouth to eyes
    wild = WILD_TARGET_MM if found is None else 1e3 * WILD_TARGET_SPANS * found[2]
    for cond in protocol.conditions:
        method = get(cond.method)
        driven = method.driven_targets(avatar, cond.settings, base_dir=base_dir)
        motion = target_motion_mm(avatar, driven)
        playback = method.playback(avatar, cond.settings, base_dir=base_dir)
        if playback.stand_in:
            rows.append(info(None, clip="", condition=cond.id, check=CHECK, measure="stand_in",
                             note=playback.stand_in))  # fmt: skip
        for name in sorted(motion):
            rows.append(at_least(
                EMPTY_TARGET_MM, motion[name], clip="", condition=cond.id, check=CHECK,
                measure=f"target_motion_mm:{name}", unit=" mm",
                note="" if motion[name] >= EMPTY_TARGET_MM else
                f"{name} moves nothing visible at full weight: the method cannot show it",
            ))  # fmt: skip
            if motion[name] > wild:  # only then: a row per target would be noise
                rows.append(at_most(
                    wild, motion[name], clip="", condition=cond.id, check=CHECK,
                    measure=f"target_reach_mm:{name}", unit=" mm",
                    note=f"{name} moves a vertex {motion[name]:.0f} mm at full weight, further "
                    f"than the face's mouth-to-eyes distance ({wild:.0f} mm): the shapes were "
                    "exported at another scale than the mesh or are broken - the face would "
                    "tear",
                ))  # fmt: skip
        if motion:
            pairs = identical_targets(avatar, driven)
            rows.append(at_most(
                0, len(pairs), clip="", condition=cond.id, check=CHECK,
                measure="identical_driven_targets", note=_same_shapes(pairs),
            ))  # fmt: skip
    rows += orientation_rows(avatar)
    rows += landmark_rows(avatar)
    gaze_used = any(c.behaviour != "none" for c in protocol.conditions)
    rows += eye_rows(avatar, severity="error" if gaze_used else "warning")
    return rows


def orientation_rows(avatar: Avatar) -> list[CheckRow]:
    """The face upright (eyes above the mouth: ``face_upright``, the cosine with +Y at least
    0.5 - the default head's line leans 17 degrees, so a head bowed or raised 30 degrees
    passes) and towards the camera (the lids' surface facing +Z: ``face_towards_camera``,
    the Z of its mean normal above 0; a warning) - a model exported Z-up, turned away (-Z
    forward) or with its triangles wound inside out renders a face the tracker cannot find,
    or none; no rows without a mouth-opening and an eye-closing shape."""
    found = face_orientation(avatar)
    if found is None:
        return []
    up, towards, _ = found
    return [
        at_least(0.5, up, clip="", condition="", check=CHECK, measure="face_upright",
                 note="" if up >= 0.5 else "the eyes are not above the mouth: the model lies "
                 "down or stands on its head (exported Z-up? glTF is Y-up: rotate it -90 "
                 "degrees about X on export)"),
        at_least(0.0, towards, clip="", condition="", check=CHECK, measure="face_towards_camera",
                 note="" if towards > 0 else "the face looks away from the camera (-Z): the "
                 "model faces -Z (VRM 0.x does; export it as VRM, or turn it 180 degrees "
                 "about Y) or its triangles are wound inside out (flip the normals)",
                 severity="warning"),  # a deep mouth cavity the jaw moves could tip it
    ]  # fmt: skip


def _same_shapes(pairs: list[tuple[str, str]]) -> str:
    """Identical pairs as groups: "a is the same shape as b" or "a = b = c are one shape"."""
    group: dict[str, set[str]] = {}
    for a, b in pairs:
        merged = group.get(a, {a}) | group.get(b, {b})
        for name in merged:
            group[name] = merged
    seen, out = set(), []
    for names in group.values():
        key = tuple(sorted(names))
        if key in seen:
            continue
        seen.add(key)
        out.append(f"{key[0]} is the same shape as {key[1]}" if len(key) == 2
                   else f"{' = '.join(key)} are one shape")  # fmt: skip
    return "; ".join(out)


def landmark_rows(avatar: Avatar) -> list[CheckRow]:
    """Whether the lip landmarks lie where a mouth is (see the module docstring)."""
    lm = avatar.landmarks
    if not all(k in lm for k in LANDMARKS):
        note = "the file has no lip landmarks: the face tracker measures the mouth"
        return [info(None, clip="", condition="", check=CHECK, measure="lip_landmarks",
                     note=note)]  # fmt: skip
    up, lo, left, right = (avatar.neutral[lm[k]].astype(float) for k in LANDMARKS)
    width_mm = (left[0] - right[0]) * 1e3
    problems = []
    if up[1] < lo[1] - 5e-4:
        problems.append("the upper lip is below the lower lip")
    if not 15 <= width_mm <= 90:
        problems.append(f"the corners are {width_mm:.1f} mm apart (a mouth: 15-90 mm)")
    for name, p in (("upper lip", up), ("lower lip", lo)):
        if not right[0] - 1e-3 <= p[0] <= left[0] + 1e-3:
            problems.append(f"the {name} is not between the corners")
    if abs(up[1] - left[1]) > 0.03 or abs(lo[1] - right[1]) > 0.03:
        problems.append("the lips are more than 30 mm above or below the corners")
    return [CheckRow("", "", CHECK, "lip_landmarks_consistent", float(not problems), "= 1",
                     not problems, "; ".join(problems))]  # fmt: skip


def eye_rows(avatar: Avatar, *, severity: str) -> list[CheckRow]:
    """Per eye joint: the pivot's depth behind the eye's front, the safe turn (the angle
    that moves the eye's front by a third of its width: ``gaze_range_deg``, reported) and the
    turn the largest planned gaze gets through the avatar's gaze map (``gaze_played_deg``,
    judged against the safe turn); a gaze shown by shapes is reported as such."""
    gaze = gaze_map(avatar)
    rows: list[CheckRow] = [info(None, clip="", condition="", check=CHECK, measure="gaze_shown_by",
                                 note=gaze.describe())]  # fmt: skip
    for role in ("eye_left", "eye_right"):
        sk = avatar.skeleton
        if sk is None or role not in sk.roles:
            continue
        measured = safe_eye_angle(avatar, role)
        if measured is None:
            rows.append(info(None, clip="", condition="", check=CHECK, measure=f"{role}_pivot",
                             note=f"no vertices follow the {role} joint"))  # fmt: skip
            continue
        safe, depth, eye_width = measured
        rows.append(info(depth * 1e3, clip="", condition="", check=CHECK,
                         measure=f"eye_pivot_depth_mm:{role}",
                         note=f"eye {eye_width * 1e3:.1f} mm wide"))  # fmt: skip
        rows.append(info(safe, clip="", condition="", check=CHECK,
                         measure=f"gaze_range_deg:{role}",
                         note="the eye-joint turn that keeps the iris inside the eye"))  # fmt: skip
        if gaze.mode != "joints":
            continue
        played = max(abs(v) for v in (*gaze.joint_angles(GAZE_RANGE_DEG, 0.0),
                                      *gaze.joint_angles(0.0, GAZE_RANGE_DEG),
                                      *gaze.joint_angles(0.0, -GAZE_RANGE_DEG)))  # fmt: skip
        moved_mm = depth * np.sin(np.radians(played)) * 1e3
        rows.append(at_most(
            round(safe, 2), played, clip="", condition="", check=CHECK,
            measure=f"gaze_played_deg:{role}", severity=severity, unit=" deg",
            note=f"a {GAZE_RANGE_DEG:g} deg gaze turns the eye joint {played:.1f} deg "
            f"({gaze.source})" + ("" if played <= safe + 0.01 else
            f": about a point {depth * 1e3:.0f} mm behind the eye's front, the iris moves "
            f"{moved_mm:.0f} mm, past the eye's edge"),
        ))  # fmt: skip
    return rows
