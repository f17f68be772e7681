"""Recognising avatar files (Ready Player Me, VRM 0.x, VRM 1.0) and mapping their names.

VRM keeps its facial expressions outside the morph-target names: VRM 0.x in
``extensions.VRM.blendShapeMaster.blendShapeGroups`` (``presetName`` a, i, u, e, o, blink,
blink_l, blink_r, joy, angry, sorrow, fun, …; binds ``{mesh, index, weight 0–100}``), VRM 1.0
in ``extensions.VRMC_vrm.expressions.preset`` (aa, ih, ou, ee, oh, blink, blinkLeft,
blinkRight, happy, angry, sad, relaxed, surprised, …; binds ``{node, index, weight 0–1}``).
Each preset becomes one target - the weighted sum of its binds - under facelab's name:

* the vowels become viseme targets: aa → ``viseme_aa``, ih → ``viseme_ih``, ou →
  ``viseme_ou``, ee → ``viseme_E``, oh → ``viseme_oh`` (so the viseme baseline plays on any
  VRM, and the vowel-driven method can use them as stand-ins for its ARKit Z);
* blinks become ``eyeBlinkLeft`` / ``eyeBlinkRight`` (a both-eyes blink is split by side
  where the model has no one-eye presets);
* emotions and the rest keep their VRM 1.0 name with a ``vrm_`` prefix (``vrm_happy``…).

A name the file's own morph targets already provide (an ARKit-named VRM) is not replaced.
VRM 0.x models face −z; they are turned 180° about the vertical axis to face the camera (+z)
like every other glTF. ``avatar.source["presets"]`` records which target stands in for which
preset. Humanoid bones (head, neck, leftEye, rightEye) give the rig's roles.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from facelab.stimuli.avatar.mesh import Avatar

__all__ = ["VOWEL_PRESET_TARGETS", "apply_vrm", "detect_kind", "humanoid_nodes"]

#: VRM 0.x preset names -> VRM 1.0 names
_VRM0_TO_1 = {
    "a": "aa", "i": "ih", "u": "ou", "e": "ee", "o": "oh",
    "blink": "blink", "blink_l": "blinkLeft", "blink_r": "blinkRight",
    "joy": "happy", "angry": "angry", "sorrow": "sad", "fun": "relaxed",
    "lookup": "lookUp", "lookdown": "lookDown", "lookleft": "lookLeft",
    "lookright": "lookRight", "neutral": "neutral",
}  # fmt: skip

#: VRM 1.0 preset -> facelab target name
_TARGET_OF = {
    "aa": "viseme_aa", "ih": "viseme_ih", "ou": "viseme_ou", "ee": "viseme_E", "oh": "viseme_oh",
    "blinkLeft": "eyeBlinkLeft", "blinkRight": "eyeBlinkRight",
}  # fmt: skip

#: the five vowel targets in a, i, u, e, o order (what stands in for Z on a VRM)
VOWEL_PRESET_TARGETS = ("viseme_aa", "viseme_ih", "viseme_ou", "viseme_E", "viseme_oh")

_HUMANOID_ROLES = {"neck": "neck", "head": "head", "leftEye": "eye_left", "rightEye": "eye_right"}


def detect_kind(doc: Any) -> str:
    """``vrm1``, ``vrm0``, ``rpm`` (Ready Player Me: Wolf3D meshes or RPM's viseme names with
    ARKit shapes) or ``gltf``."""
    ext = doc.extensions or {}
    if "VRMC_vrm" in ext:
        return "vrm1"
    if "VRM" in ext:
        return "vrm0"
    names = [m.name or "" for m in doc.meshes or []]
    targets = {
        str(n).lower()
        for m in doc.meshes or []
        for n in ((m.extras or {}).get("targetNames", []) if isinstance(m.extras, dict) else [])
    }
    generator = str(getattr(doc.asset, "generator", "") or "").lower()
    if generator.startswith("facelab"):
        return "gltf"
    if (
        any(n.startswith("Wolf3D_") for n in names)
        or "readyplayer" in generator
        or ({"viseme_aa", "viseme_pp"} <= targets and "jawopen" in targets)
    ):
        return "rpm"
    return "gltf"


def humanoid_nodes(doc: Any) -> dict[str, int]:
    """{rig role: node index} from the VRM humanoid (head, neck, eyes)."""
    ext = doc.extensions or {}
    out: dict[str, int] = {}
    if "VRMC_vrm" in ext:
        bones = (ext["VRMC_vrm"].get("humanoid") or {}).get("humanBones") or {}
        for bone, role in _HUMANOID_ROLES.items():
            node = (bones.get(bone) or {}).get("node")
            if isinstance(node, int):
                out[role] = node
    elif "VRM" in ext:
        for entry in (ext["VRM"].get("humanoid") or {}).get("humanBones") or []:
            role = _HUMANOID_ROLES.get(entry.get("bone", ""))
            if role and isinstance(entry.get("node"), int):
                out[role] = entry["node"]
    return out


def _presets(doc: Any) -> dict[str, list[tuple[int, int, float]]]:
    """{VRM 1.0 preset name: [(mesh index, target index, weight 0–1)]}."""
    ext = doc.extensions or {}
    out: dict[str, list[tuple[int, int, float]]] = {}
    if "VRMC_vrm" in ext:
        expressions = ext["VRMC_vrm"].get("expressions") or {}
        nodes = doc.nodes or []
        for group in ("preset", "custom"):
            for name, expr in (expressions.get(group) or {}).items():
                binds = []
                for b in expr.get("morphTargetBinds") or []:
                    node = b.get("node")
                    if isinstance(node, int) and node < len(nodes) and nodes[node].mesh is not None:
                        binds.append((nodes[node].mesh, int(b["index"]), float(b.get("weight", 1))))
                out[name] = binds
    elif "VRM" in ext:
        groups = (ext["VRM"].get("blendShapeMaster") or {}).get("blendShapeGroups") or []
        for g in groups:
            preset = str(g.get("presetName") or "unknown").lower()
            name = _VRM0_TO_1.get(preset) or str(g.get("name") or preset)
            out[name] = [
                (int(b["mesh"]), int(b["index"]), float(b.get("weight", 100)) / 100.0)
                for b in g.get("binds") or []
            ]
    return out


def apply_vrm(
    avatar: Avatar, doc: Any, raw_targets: dict[tuple[int, int], list[tuple[int, np.ndarray]]]
) -> Avatar:
    """Add preset targets (see the module docstring); turn VRM 0.x to face +z."""
    kind = avatar.source.get("kind", "")
    targets = dict(avatar.targets)
    own = set(targets)
    n = len(avatar.neutral)
    made: dict[str, str] = {}
    for preset, binds in _presets(doc).items():
        delta = np.zeros((n, 3), np.float64)
        for mesh, index, weight in binds:
            for start, d in raw_targets.get((mesh, index), []):
                delta[start : start + len(d)] += weight * d
        if not binds or not np.any(delta):
            continue
        name = _TARGET_OF.get(preset, f"vrm_{preset}")
        if name not in own:
            targets[name] = delta.astype(np.float32)
            made[name] = preset
    result = avatar.replace(targets=targets)
    if kind == "vrm0":
        result = _turn_around(result)
    presets = set(made.values())
    if "blink" in presets and not {"blinkLeft", "blinkRight"} & presets:
        targets = dict(result.targets)
        both = targets["vrm_blink"]
        x = result.neutral[:, 0]  # now +x is the avatar's left for every kind
        for name, side in (("eyeBlinkLeft", x > 0), ("eyeBlinkRight", x <= 0)):
            if name not in own:
                targets[name] = np.where(side[:, None], both, 0.0).astype(np.float32)
                made[name] = "blink (one side)"
        result = result.replace(targets=targets)
    look = _look_at(doc)
    return result.replace(
        source={**avatar.source, "presets": made, **({"look_at": look} if look else {})}
    )


#: VRM 1.0 range-map names -> facelab's gaze directions (horizontal outer/inner: the eye
#: turning away from / towards the nose)
_RANGE_MAPS = {"rangeMapHorizontalOuter": "out", "rangeMapHorizontalInner": "in",
               "rangeMapVerticalUp": "up", "rangeMapVerticalDown": "down"}  # fmt: skip
_VRM0_RANGE_MAPS = {"lookAtHorizontalOuter": "out", "lookAtHorizontalInner": "in",
                    "lookAtVerticalUp": "up", "lookAtVerticalDown": "down"}  # fmt: skip


def _look_at(doc: Any) -> dict[str, Any] | None:
    """The file's lookAt as {"type": "bone" | "expression", "ranges": {direction: [input max
    deg, output]}} (output: degrees of eye-bone turn, or expression weight), or None."""
    ext = doc.extensions or {}
    if "VRMC_vrm" in ext:
        look = ext["VRMC_vrm"].get("lookAt")
        if not isinstance(look, dict):
            return None
        kind = "bone" if look.get("type", "bone") == "bone" else "expression"
        maps = {d: look.get(k) for k, d in _RANGE_MAPS.items()}
        ranges = {d: [float(m.get("inputMaxValue", 90.0)), float(m.get("outputScale", 10.0))]
                  for d, m in maps.items() if isinstance(m, dict)}  # fmt: skip
    elif "VRM" in ext:
        look = ext["VRM"].get("firstPerson")
        if not isinstance(look, dict) or not any(k in look for k in _VRM0_RANGE_MAPS):
            return None
        kind = "bone" if str(look.get("lookAtTypeName", "Bone")) == "Bone" else "expression"
        maps = {d: look.get(k) for k, d in _VRM0_RANGE_MAPS.items()}
        ranges = {d: [float(m.get("xRange", 90.0)), float(m.get("yRange", 10.0))]
                  for d, m in maps.items() if isinstance(m, dict)}  # fmt: skip
    else:
        return None
    ranges = {d: r for d, r in ranges.items() if r[0] > 0 and r[1] >= 0}
    return {"type": kind, "ranges": ranges} if ranges else None


def _turn_around(avatar: Avatar) -> Avatar:
    """Rotate 180° about the vertical axis (x -> -x, z -> -z)."""
    flip = np.array([-1.0, 1.0, -1.0], np.float32)
    sk = avatar.skeleton
    if sk is not None:
        sk = type(sk)(sk.names, sk.parents, sk.pivots * flip, sk.joints, sk.weights, sk.roles)
    return avatar.replace(
        neutral=avatar.neutral * flip,
        targets={k: v * flip for k, v in avatar.targets.items()},
        skeleton=sk,
    )
