"""The rig: a skeleton that turns the head, neck and eyes by linear blend skinning.

Everything is expressed in the avatar's **rest world frame** (metres; x to the avatar's left,
y up, z forward towards the viewer), so one formula serves every source - the default head,
skinned glTF, Ready Player Me and VRM files: a joint ``j`` with rest pivot ``p_j`` and a
rotation ``R_j`` about world axes has the skinning matrix

    M_j = M_parent(j) · T(p_j) · R_j · T(-p_j)        (M_root's parent = identity)

and a vertex with joints ``j_k`` and weights ``w_k`` (k < 4) moves to
``Σ_k w_k · M_{j_k} · v`` (morph targets are applied first, as in glTF 2.0 §3.7.3).

Angles are degrees. ``yaw`` turns about the vertical axis, positive towards the avatar's
left (the viewer's right); ``pitch`` about the ear-to-ear axis, positive chin down;
``roll`` about the forward axis, positive tilts the top of the head towards the avatar's
right (the viewer's left). Eye ``yaw``/``pitch`` follow the same signs, relative to the head.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from facelab.errors import AvatarError

__all__ = [
    "ROLES",
    "HeadPose",
    "Skeleton",
    "euler_matrix",
    "gaze_weights",
    "match_roles",
    "skin",
]

#: the joints the behaviour layer drives
ROLES = ("neck", "head", "eye_left", "eye_right")


@dataclass(frozen=True)
class HeadPose:
    """Head, neck and eye rotation in degrees (see the module docstring for the signs).

    ``yaw``/``pitch``/``roll`` are the head's total rotation relative to the torso; the neck
    takes ``neck_share`` of it and the head the rest (where the avatar has no neck joint the
    head takes all). ``eye_yaw``/``eye_pitch`` turn the eyes relative to the head.
    """

    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    eye_yaw: float = 0.0
    eye_pitch: float = 0.0
    neck_share: float = 0.4

    def is_rest(self) -> bool:
        return not any((self.yaw, self.pitch, self.roll, self.eye_yaw, self.eye_pitch))


def euler_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) rotation R = Ry(yaw) · Rx(pitch) · Rz(roll), angles in degrees."""
    y, p, r = np.radians([yaw, pitch, roll])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return ry @ rx @ rz


def _rows(idx: np.ndarray) -> np.ndarray | slice:
    """``idx`` (sorted vertex indices) as a slice when they are one run (a mesh part's
    vertices usually are): slicing copies nothing and writes in place."""
    if idx.size and int(idx[-1]) - int(idx[0]) + 1 == idx.size:
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


@dataclass(frozen=True)
class _Influence:
    """The vertices some moved joint influences, split for speed: ``rigid[u]`` the vertices
    bound to joint ``used[u]`` alone (weight 1: most vertices of a head; a slice when they
    are one run of indices), ``blend`` the others (B,), with ``blend_matrix`` (B, U) float32
    their weight on each joint in ``used`` (every joint of these vertices, moved or not)."""

    size: int
    used: np.ndarray
    rigid: tuple[np.ndarray | slice, ...]
    blend: np.ndarray
    blend_matrix: np.ndarray

    @classmethod
    def of(cls, skeleton: Skeleton, moved: tuple[int, ...]) -> _Influence:
        hit = np.isin(skeleton.joints, np.asarray(moved, np.int64)) & (skeleton.weights > 0)
        rows = np.nonzero(hit.any(axis=1))[0]
        weights = skeleton.weights[rows]
        used, local = np.unique(skeleton.joints[rows], return_inverse=True)
        local = local.reshape(-1, 4)
        top = np.argmax(weights, axis=1)
        # bound to one joint: its weight is 1 and the others are 0 (not merely the largest)
        alone = np.isclose(weights.max(axis=1), 1.0, atol=1e-6) & np.isclose(
            weights.sum(axis=1), 1.0, atol=1e-6
        )
        owner = local[np.arange(len(rows)), top]
        rigid = tuple(_rows(rows[alone & (owner == u)]) for u in range(len(used)))
        blend = np.nonzero(~alone)[0]
        matrix = np.zeros((len(blend), len(used)), np.float32)
        for k in range(local.shape[1]):
            np.add.at(matrix, (np.arange(len(blend)), local[blend, k]), weights[blend, k])
        return cls(
            int(rows.size),
            used,
            rigid,
            rows[blend],
            matrix,
        )


@dataclass
class Skeleton:
    """Joints and per-vertex skin weights, all in the rest world frame.

    names (J,); parents (J,) int with -1 for a root and every parent listed before its
    children; pivots (J, 3) rest joint positions, m; joints (V, 4) int and weights (V, 4)
    float (rows sum to 1; a row of zeros leaves the vertex where it is); roles
    {role: joint index} for :data:`ROLES` that the avatar has.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    pivots: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    roles: dict[str, int] = field(default_factory=dict)
    # moved joints -> how they reach the vertices (see influence())
    _influence: dict[tuple[int, ...], _Influence] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        self.parents = np.asarray(self.parents, np.int64)
        self.pivots = np.asarray(self.pivots, np.float64).reshape(-1, 3)
        self.joints = np.ascontiguousarray(self.joints, np.int64)
        self.weights = np.ascontiguousarray(self.weights, np.float32)
        n = len(self.names)
        if self.parents.shape != (n,) or self.pivots.shape != (n, 3):
            raise AvatarError(f"skeleton: {n} joint names but parents/pivots do not match")
        if any(p >= i for i, p in enumerate(self.parents)):
            raise AvatarError("skeleton: every parent must come before its children")
        if self.joints.shape != self.weights.shape or self.joints.shape[1:] != (4,):
            raise AvatarError("skeleton: joints and weights must both be (V, 4)")
        if self.joints.size and (self.joints.min() < 0 or self.joints.max() >= n):
            raise AvatarError("skeleton: a vertex refers to a joint that does not exist")
        for role, j in self.roles.items():
            if role not in ROLES or not 0 <= j < n:
                raise AvatarError(f"skeleton: bad role {role!r} -> joint {j}")

    def influence(self, moved: tuple[int, ...]) -> _Influence:
        """How the joints ``moved`` reach the vertices (see :class:`_Influence`). Cached per
        set of moved joints (a clip turns the same ones every frame)."""
        if moved not in self._influence:
            self._influence[moved] = _Influence.of(self, moved)
        return self._influence[moved]

    def descendants(self, joint: int) -> np.ndarray:
        """Indices of ``joint`` and every joint below it."""
        inside = np.zeros(len(self.names), bool)
        inside[joint] = True
        for j in range(joint + 1, len(self.names)):
            if self.parents[j] >= 0 and inside[self.parents[j]]:
                inside[j] = True
        return np.nonzero(inside)[0]

    def vertices_of(self, joint: int, *, min_weight: float = 0.5) -> np.ndarray:
        """Vertex indices whose weight on ``joint`` and the joints below it is ≥ min_weight."""
        below = np.isin(self.joints, self.descendants(joint))
        return np.nonzero((self.weights * below).sum(axis=1) >= min_weight)[0]

    def matrices(self, rotations: Mapping[int, np.ndarray]) -> np.ndarray:
        """(J, 4, 4) skinning matrices for world-axis rotations {joint: (3, 3)} about pivots."""
        n = len(self.names)
        out = np.tile(np.eye(4), (n, 1, 1))
        for j in range(n):
            local = np.eye(4)
            rot = rotations.get(j)
            if rot is not None:
                local[:3, :3] = rot
                local[:3, 3] = self.pivots[j] - rot @ self.pivots[j]
            parent = self.parents[j]
            out[j] = (out[parent] @ local) if parent >= 0 else local
        return out

    def pose_rotations(self, pose: HeadPose) -> dict[int, np.ndarray]:
        """The world-axis rotation per joint that realises ``pose`` on this skeleton."""
        roles = self.roles
        if "head" not in roles and (pose.yaw or pose.pitch or pose.roll):
            raise AvatarError("this avatar's skeleton has no head joint to turn")
        rot: dict[int, np.ndarray] = {}
        share = pose.neck_share if "neck" in roles else 0.0
        if "neck" in roles and share:
            rot[roles["neck"]] = euler_matrix(
                pose.yaw * share, pose.pitch * share, pose.roll * share
            )
        if "head" in roles:
            rest = 1.0 - share
            rot[roles["head"]] = euler_matrix(pose.yaw * rest, pose.pitch * rest, pose.roll * rest)
        if pose.eye_yaw or pose.eye_pitch:
            eye = euler_matrix(pose.eye_yaw, pose.eye_pitch, 0.0)
            for role in ("eye_left", "eye_right"):
                if role in roles:
                    rot[roles[role]] = eye
        return rot


def skin(vertices: np.ndarray, skeleton: Skeleton, pose: HeadPose) -> np.ndarray:
    """Vertices (V, 3) posed by linear blend skinning (a float32 copy; unmoved rows are
    unchanged): ``v' = sum_k w_k (R_jk v + t_jk)`` over each vertex's four influences.

    Only the rows that a moved joint influences are touched: rows bound to one joint are
    moved by that joint's transform (one matmul per joint, in place when they are one run of
    indices); each of the others gets its weighted blend of the joints' 3x4 transforms (one
    (B, U) x (U, 12) product) applied to it."""
    rotations = skeleton.pose_rotations(pose)
    if not rotations:
        return np.array(vertices, np.float32, copy=True)
    mats = skeleton.matrices(rotations)
    moved = tuple(np.nonzero(~np.all(np.isclose(mats, np.eye(4)), axis=(1, 2)))[0].tolist())
    out = np.array(vertices, np.float32, copy=True)
    inf = skeleton.influence(moved)
    if inf.size == 0:
        return out
    v = np.asarray(vertices, np.float32)
    m = mats[inf.used].astype(np.float32)  # (U, 4, 4)
    for u, idx in enumerate(inf.rigid):
        out[idx] = v[idx] @ m[u, :3, :3].T + m[u, :3, 3]
    if inf.blend.size:
        vb = v[inf.blend]  # (B, 3)
        blended = (inf.blend_matrix @ m[:, :3, :].reshape(len(m), 12)).reshape(-1, 3, 4)
        out[inf.blend] = np.einsum("bij,bj->bi", blended[:, :, :3], vb) + blended[:, :, 3]
    return out


def gaze_weights(eye_yaw: float, eye_pitch: float, *, range_deg: float = 25.0) -> dict[str, float]:
    """ARKit ``eyeLook*`` weights for a gaze direction (degrees; avatars without eye joints).

    A weight of 1 is taken as ``range_deg`` of rotation (the default head's eyeLook targets
    turn the eyeball 25°). Yaw towards the avatar's left is eyeLookOutLeft + eyeLookInRight.
    """
    h = float(np.clip(eye_yaw / range_deg, -1, 1))
    v = float(np.clip(eye_pitch / range_deg, -1, 1))
    out = {
        name: 0.0
        for side in ("Left", "Right")
        for name in (
            f"eyeLookOut{side}",
            f"eyeLookIn{side}",
            f"eyeLookUp{side}",
            f"eyeLookDown{side}",
        )
    }
    if h > 0:
        out["eyeLookOutLeft"] = out["eyeLookInRight"] = h
    elif h < 0:
        out["eyeLookInLeft"] = out["eyeLookOutRight"] = -h
    if v > 0:
        out["eyeLookDownLeft"] = out["eyeLookDownRight"] = v
    elif v < 0:
        out["eyeLookUpLeft"] = out["eyeLookUpRight"] = -v
    return out


# joint names of common rigs -> role, matched case-insensitively after stripping a namespace
# ("mixamorig:", "Armature|") and VRoid's "J_Bip_C_" / "J_Adj_" prefixes
_ROLE_PATTERNS: dict[str, str] = {
    "neck": r"neck(_?0?1)?",
    "head": r"head",
    "eye_left": r"left_?eye|eye_?l(eft)?|l_?(face)?eye|facial_l_eye|eye\.l",
    "eye_right": r"right_?eye|eye_?r(ight)?|r_?(face)?eye|facial_r_eye|eye\.r",
}


def match_roles(names: tuple[str, ...] | list[str]) -> dict[str, int]:
    """{role: joint index} found by name (Ready Player Me, Mixamo, VRoid, MetaHuman, Blender);
    the first joint matching a role wins."""
    out: dict[str, int] = {}
    for i, raw in enumerate(names):
        key = re.sub(r"^.*[:|]", "", raw.strip().lower())
        key = re.sub(r"^(j_bip_c_|j_bip_|j_adj_|j_)", "", key)
        for role, pattern in _ROLE_PATTERNS.items():
            if role not in out and re.fullmatch(pattern, key):
                out[role] = i
    return out
