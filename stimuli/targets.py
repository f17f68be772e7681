"""Which blendshape targets each animation method needs, and viseme shapes built from ARKit
mixes for avatars that have none."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from facelab.errors import AvatarError
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS
from facelab.stimuli.drive import load_z
from facelab.stimuli.mesh import Avatar
from facelab.stimuli.vrm import VOWEL_PRESET_TARGETS

__all__ = [
    "VISEME_METHODS",
    "VISEME_MIXES",
    "check_targets",
    "required_targets",
    "uses_vowel_presets",
    "vowel_presets_only",
    "with_viseme_mixes",
]


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
    "viseme_E": {
        "jawOpen": 0.3,
        "mouthStretchLeft": 0.4,
        "mouthStretchRight": 0.4,
        "mouthSmileLeft": 0.15,
        "mouthSmileRight": 0.15,
    },
    "viseme_ih": {
        "jawOpen": 0.15,
        "mouthStretchLeft": 0.45,
        "mouthStretchRight": 0.45,
        "mouthSmileLeft": 0.25,
        "mouthSmileRight": 0.25,
    },
    "viseme_oh": {"jawOpen": 0.35, "mouthFunnel": 0.6, "mouthPucker": 0.2},
    "viseme_ou": {"jawOpen": 0.1, "mouthPucker": 0.7, "mouthFunnel": 0.3},
}


#: the methods that drive ``viseme_*`` targets
VISEME_METHODS = ("viseme_baseline", "text_visemes")


def required_targets(method: str, params: Mapping | None = None) -> set[str]:
    """Targets a method drives: vowel_blend the ARKit rows its Z uses; viseme methods the 14
    viseme shapes (or, failing those, the ARKit shapes their mixes use); impression the ARKit
    channels its model moves (checked when the clip is built: the model file is read there)."""
    if method == "impression":
        return set()
    if method == "vowel_blend":
        z = load_z(str((params or {}).get("z", "standard")))
        return {n for n, row in zip(ARKIT_NAMES, z, strict=True) if np.any(row > 0)}
    return set(VISEME_TARGETS[1:])


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


def uses_vowel_presets(avatar: Avatar, method: str, params: Mapping | None = None) -> bool:
    """True when ``vowel_blend`` must play on a VRM's vowel presets (aa ih ou ee oh) because
    the avatar lacks ARKit targets its Z uses."""
    if method != "vowel_blend" or not str(avatar.source.get("kind", "")).startswith("vrm"):
        return False
    if required_targets(method, params) <= set(avatar.targets):
        return False
    return set(VOWEL_PRESET_TARGETS) <= set(avatar.targets)


def check_targets(avatar: Avatar, method: str, params: Mapping | None = None) -> None:
    """Raise listing every target ``method`` needs that ``avatar`` lacks."""
    if uses_vowel_presets(avatar, method, params) or (
        method in VISEME_METHODS and vowel_presets_only(avatar)
    ):
        return
    need = required_targets(method, params)
    if method in VISEME_METHODS and not need <= set(avatar.targets):
        mixes = {n for v in need for n in VISEME_MIXES[v]}
        missing = sorted(need - set(avatar.targets))
        lacking_mix = sorted(mixes - set(avatar.targets))
        if lacking_mix:
            raise AvatarError(
                f"avatar {avatar.name!r} lacks targets for method {method!r}: "
                f"{', '.join(missing)} (and the ARKit shapes to build them: "
                f"{', '.join(lacking_mix)})"
            )
        return
    missing = sorted(need - set(avatar.targets))
    if missing:
        raise AvatarError(
            f"avatar {avatar.name!r} lacks {len(missing)} target(s) that method "
            f"{method!r} needs: {', '.join(missing)}"
        )
