"""Viseme shapes built from ARKit mixes for avatars that have none, and the VRM case of an
avatar whose only mouth shapes are its five vowel presets. (Which targets each animation
method needs is the method's own: ``facelab.stimuli.methods``.)"""

from __future__ import annotations

import numpy as np

from facelab.errors import AvatarError
from facelab.stimuli.arkit import VISEME_TARGETS
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.vrm import VOWEL_PRESET_TARGETS

__all__ = ["VISEME_MIXES", "vowel_presets_only", "with_viseme_mixes"]


#: viseme target -> ARKit mix used when an avatar has no viseme_* shapes (and by the
#: default head). Written from the ARKit semantics and the Oculus viseme reference images.
VISEME_MIXES: dict[str, dict[str, float]] = {
    "viseme_sil": {},
    "viseme_PP": {
        "mouthPressLeft": 0.6,
        "mouthPressRight": 0.6,
        "mouthRollLower": 0.35,
        "mouthRollUpper": 0.3,
        "mouthClose": 0.05,
        "jawOpen": 0.05,
    },
    "viseme_FF": {
        "mouthRollLower": 0.6,
        "mouthUpperUpLeft": 0.2,
        "mouthUpperUpRight": 0.2,
        "mouthShrugUpper": 0.2,
        "jawOpen": 0.08,
    },
    "viseme_TH": {
        "jawOpen": 0.15,
        "tongueOut": 0.35,
        "mouthUpperUpLeft": 0.1,
        "mouthUpperUpRight": 0.1,
    },
    "viseme_DD": {"jawOpen": 0.2, "mouthStretchLeft": 0.15, "mouthStretchRight": 0.15},
    "viseme_kk": {"jawOpen": 0.25, "mouthStretchLeft": 0.15, "mouthStretchRight": 0.15},
    "viseme_CH": {"mouthFunnel": 0.5, "mouthPucker": 0.2, "jawOpen": 0.15},
    "viseme_SS": {
        "jawOpen": 0.08,
        "mouthStretchLeft": 0.35,
        "mouthStretchRight": 0.35,
        "mouthSmileLeft": 0.1,
        "mouthSmileRight": 0.1,
    },
    "viseme_nn": {"jawOpen": 0.15, "mouthStretchLeft": 0.1, "mouthStretchRight": 0.1},
    "viseme_RR": {"mouthPucker": 0.3, "mouthFunnel": 0.2, "jawOpen": 0.15},
    "viseme_aa": {"jawOpen": 0.6, "mouthLowerDownLeft": 0.3, "mouthLowerDownRight": 0.3},
    "viseme_E": {  # mid-open and spread, the lower lip down off the teeth (as Z's e)
        "jawOpen": 0.3,
        "mouthStretchLeft": 0.4,
        "mouthStretchRight": 0.4,
        "mouthSmileLeft": 0.15,
        "mouthSmileRight": 0.15,
        "mouthLowerDownLeft": 0.2,
        "mouthLowerDownRight": 0.2,
        "mouthUpperUpLeft": 0.1,
        "mouthUpperUpRight": 0.1,
    },
    "viseme_ih": {  # spread (the most of any vowel), the lips parted over the teeth
        "jawOpen": 0.15,
        "mouthStretchLeft": 0.5,
        "mouthStretchRight": 0.5,
        "mouthSmileLeft": 0.3,
        "mouthSmileRight": 0.3,
        "mouthLowerDownLeft": 0.15,
        "mouthLowerDownRight": 0.15,
        "mouthUpperUpLeft": 0.1,
        "mouthUpperUpRight": 0.1,
    },
    "viseme_oh": {"jawOpen": 0.35, "mouthFunnel": 0.6, "mouthPucker": 0.2},
    "viseme_ou": {"jawOpen": 0.1, "mouthPucker": 0.55, "mouthFunnel": 0.3},
}


def vowel_presets_only(avatar: Avatar) -> bool:
    """A VRM whose mouth shapes are just the five vowel presets (no ARKit to build visemes)."""
    return (
        str(avatar.source.get("kind", "")).startswith("vrm")
        and set(VOWEL_PRESET_TARGETS) <= set(avatar.targets)
        and not {n for mix in VISEME_MIXES.values() for n in mix} <= set(avatar.targets)
    )


def with_viseme_mixes(avatar: Avatar) -> Avatar:
    """Add ``viseme_*`` targets built from ARKit mixes where the avatar lacks them. On a VRM
    with only its five vowel presets, the consonant visemes get no shape (a zero target; the
    clip metadata says so), as VRM lip-sync does."""
    missing = [v for v in VISEME_TARGETS if v not in avatar.targets]
    if not missing:
        return avatar
    targets = dict(avatar.targets)
    if vowel_presets_only(avatar):
        for v in missing:
            targets[v] = np.zeros_like(avatar.neutral)
        return avatar.replace(targets=targets, source={**avatar.source, "zero_visemes": missing})
    for v in missing:
        mix = VISEME_MIXES[v]
        absent = [n for n in mix if n not in targets]
        if absent:
            raise AvatarError(
                f"avatar {avatar.name!r} has no {v} target and lacks the ARKit "
                f"targets to build it: {', '.join(absent)}"
            )
        delta = np.zeros_like(avatar.neutral)
        for n, w in mix.items():
            delta += w * targets[n]
        targets[v] = delta
    return avatar.replace(targets=targets)
