"""The vowel-driven blendshape method (the seed's proposal)

    Y (T, 52) = clip(G * X (T, 5) @ Z.T (5, 52), 0, 1)

with X the vowel intensities a, i, u, e, o per frame and Z (52, 5) a shipped or measured
matrix (column j: the ARKit coefficients of vowel j). On a VRM without the ARKit targets its Z
uses, the five vowel presets (aa ih ou ee oh) stand in: Y = clip(G * X).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from facelab.errors import FacelabError
from facelab.methods import BUILTIN_Z, METHODS, VowelBlendParams
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.vrm import VOWEL_PRESET_TARGETS
from facelab.stimuli.capture.zmatrix import load_z
from facelab.stimuli.methods.registry import Method, Playback, register
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput

__all__ = ["VowelBlend", "vowel_presets"]

#: the VRM presets standing in for vowels a i u e o (loaded as viseme_aa … viseme_oh)
PRESET_NAMES = ("viseme_aa", "viseme_ih", "viseme_ou", "viseme_E", "viseme_oh")


def vowel_presets(inp: DriveInput, params: VowelBlendParams) -> BlendshapeTrack:
    """The vowel intensities driving an avatar's five vowel presets directly: Y = clip(G * X)
    (Z is not used)."""
    y = np.clip(params.gain * inp.track.vowels(), 0.0, 1.0)
    return BlendshapeTrack(inp.track.times, y, PRESET_NAMES)


class VowelBlend(Method):
    """Y = clip(G * X @ Z.T) over the 52 ARKit targets."""

    spec = METHODS["vowel_blend"]

    def drive(self, inp: DriveInput, params: VowelBlendParams) -> BlendshapeTrack:  # type: ignore[override]
        z_mat = load_z(params.z, base_dir=inp.base_dir)
        y = np.clip(params.gain * inp.track.vowels() @ z_mat.T, 0.0, 1.0)
        return BlendshapeTrack(inp.track.times, y, ARKIT_NAMES)

    def targets(self, params: VowelBlendParams, *, base_dir: Path = Path(".")) -> set[str]:  # type: ignore[override]
        """The ARKit rows its Z uses."""
        z = load_z(params.z, base_dir=base_dir)
        return {n for n, row in zip(ARKIT_NAMES, z, strict=True) if np.any(row > 0)}

    def input_files(self, params: VowelBlendParams) -> dict[str, str]:  # type: ignore[override]
        return {"z": params.z} if params.z.lower().endswith(".csv") else {}

    def input_problems(  # type: ignore[override]
        self, params: VowelBlendParams, *, base_dir: Path, where: tuple[str, ...] = ("params",)
    ) -> Iterator[tuple[tuple[str, ...], str]]:
        try:
            load_z(params.z, base_dir=base_dir)
        except FacelabError as exc:
            yield (*where, "z"), str(exc)

    def examples(self) -> tuple[VowelBlendParams, ...]:
        """Both shipped Z matrices."""
        return tuple(VowelBlendParams(z=z) for z in BUILTIN_Z)

    def _presets(self, avatar: Avatar, params: VowelBlendParams, base_dir: Path) -> bool:
        """True when the VRM's vowel presets must stand in for the ARKit targets."""
        return (
            str(avatar.source.get("kind", "")).startswith("vrm")
            and not self.targets(params, base_dir=base_dir) <= set(avatar.targets)
            and set(VOWEL_PRESET_TARGETS) <= set(avatar.targets)
        )

    def playback(
        self, avatar: Avatar, params: VowelBlendParams, *, base_dir: Path = Path(".")
    ) -> Playback:  # type: ignore[override]
        if self._presets(avatar, params, base_dir):
            return Playback(
                True,
                "vowel presets (aa ih ou ee oh stand in for Z: Y = G·X)",
                f"{avatar.source.get('kind')} vowel presets aa ih ou ee oh instead of ARKit Z "
                "(Y = G * X)",
            )
        playback = super().playback(avatar, params, base_dir=base_dir)
        if playback.playable:
            return Playback(True, "yes (the ARKit targets its Z uses)")
        return playback

    def drive_on(
        self, avatar: Avatar, inp: DriveInput, params: VowelBlendParams
    ) -> BlendshapeTrack:  # type: ignore[override]
        if self._presets(avatar, params, inp.base_dir):
            return vowel_presets(inp, params)
        return self.drive(inp, params)


register(VowelBlend())
