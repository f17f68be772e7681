"""The 52 ARKit blendshape names, in one fixed order, and name matching.

Order: Apple's ``ARFaceAnchor.BlendShapeLocation`` documentation order (eyes left, eyes right,
jaw, mouth, brows, cheeks, nose, tongue). Everything else maps by name.
"""

from __future__ import annotations

import re

__all__ = ["ARKIT_NAMES", "OCULUS_VISEMES", "VISEME_TARGETS", "canonical_arkit_name"]

ARKIT_NAMES: tuple[str, ...] = (
    "eyeBlinkLeft",
    "eyeLookDownLeft",
    "eyeLookInLeft",
    "eyeLookOutLeft",
    "eyeLookUpLeft",
    "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight",
    "eyeLookDownRight",
    "eyeLookInRight",
    "eyeLookOutRight",
    "eyeLookUpRight",
    "eyeSquintRight",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawRight",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthLeft",
    "mouthRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
)
assert len(ARKIT_NAMES) == 52

#: The 15 Oculus LipSync visemes, in Oculus order (``sil`` is the neutral face).
OCULUS_VISEMES: tuple[str, ...] = (
    "sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E", "ih", "oh", "ou",
)  # fmt: skip

#: Morph-target names of the 15 Oculus visemes, in Oculus order.
VISEME_TARGETS: tuple[str, ...] = tuple(f"viseme_{v}" for v in OCULUS_VISEMES)

_BY_KEY = {name.lower(): name for name in (*ARKIT_NAMES, *VISEME_TARGETS)}
# Ready Player Me and others spell three vowel visemes differently
_ALIASES = {"viseme_i": "viseme_ih", "viseme_o": "viseme_oh", "viseme_u": "viseme_ou"}


def canonical_arkit_name(name: str) -> str | None:
    """The canonical target name for ``name`` (case-insensitive; ``_L``/``_R``, ``Left``/
    ``Right`` and ``L``/``R`` suffixes; RPM viseme spellings), or None if it is not one."""
    key = name.strip().lower().replace(" ", "")
    if key in _ALIASES:
        key = _ALIASES[key]
    key = re.sub(r"[_.]l$", "left", key)
    key = re.sub(r"[_.]r$", "right", key)
    if (
        key not in _BY_KEY
        and key.endswith(("l", "r"))
        and (key[:-1] + ("left" if key[-1] == "l" else "right")) in _BY_KEY
    ):
        key = key[:-1] + ("left" if key[-1] == "l" else "right")
    return _BY_KEY.get(key)
