"""The vowel-driven blendshape method (the seed's proposal)

    Y (T, 52) = clip(G * X (T, 5) @ Z.T (5, 52), 0, 1)

with X the vowel intensities a, i, u, e, o per frame and Z (52, 5) a shipped or measured
matrix (column j: the ARKit coefficients of vowel j).

On an avatar whose ARKit mouth cannot show Z - it lacks the targets Z uses (a VRM with only its
presets) or has them empty or as copies of each other (a VRoid export whose ``jawOpen`` moves
nothing and whose ``mouthFunnel`` is its ``mouthPucker``) - the avatar's own five vowel shapes
(``viseme_aa ih ou E oh``: VRM presets aa ih ou ee oh, a VRoid ``Fcl_MTH_*``) stand in, driven so
that Z still acts: each Z column's mouth is retargeted onto the vowel shapes
(:func:`vowel_shape_weights`, W (5, 5) fitted on the default head, which has both), and
Y = clip(G * X @ W.T) over the five shapes. Standard and emphasized Z therefore open the
avatar's mouth by different amounts, as they do on an ARKit avatar.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from facelab.errors import FacelabError
from facelab.methods import BUILTIN_Z, METHODS, VowelBlendParams
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.avatar.audit import EMPTY_TARGET_MM, unusable_targets
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.vrm import VOWEL_PRESET_TARGETS
from facelab.stimuli.capture.zmatrix import load_z
from facelab.stimuli.methods.registry import Method, Playback, register
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput
from facelab.stimuli.speech.track import VisemeTrack

__all__ = ["MOUTH_WEIGHT", "VowelBlend", "mouth_targets", "vowel_shape_weights", "vowel_shapes"]

#: the vowel shapes standing in for Z's ARKit targets, for vowels a i u e o (VRM presets are
#: loaded under these names)
PRESET_NAMES = VOWEL_PRESET_TARGETS
#: Z's mouth: the ARKit targets some vowel drives at least this much
MOUTH_WEIGHT = 0.1


def mouth_targets(z: np.ndarray) -> set[str]:
    """The ARKit targets (rows of Z (52, 5)) some vowel drives at least :data:`MOUTH_WEIGHT`."""
    return {n for n, row in zip(ARKIT_NAMES, z, strict=True) if float(row.max()) >= MOUTH_WEIGHT}


@functools.lru_cache(maxsize=1)
def _reference_fields() -> tuple[np.ndarray, np.ndarray]:
    """On the default head: (52, 3M) the ARKit targets' and (5, 3M) the vowel shapes'
    displacements of the M mouth vertices (those any of them moves by 0.5 mm or more), m."""
    from facelab.stimuli.avatar import default_head

    head = default_head()
    arkit = np.stack([head.targets[n] for n in ARKIT_NAMES]).astype(np.float64)
    shapes = np.stack([head.targets[n] for n in PRESET_NAMES]).astype(np.float64)
    mouth_shapes = np.linalg.norm(shapes, axis=2).max(axis=0) >= EMPTY_TARGET_MM * 1e-3
    return arkit[:, mouth_shapes].reshape(52, -1), shapes[:, mouth_shapes].reshape(5, -1)


@functools.lru_cache(maxsize=8)
def _shape_weights(z_bytes: bytes) -> np.ndarray:
    from scipy.optimize import nnls

    z = np.frombuffer(z_bytes, np.float64).reshape(52, 5)
    arkit, shapes = _reference_fields()
    wanted = z.T @ arkit  # (5, 3M): each vowel's mouth under Z on the default head
    w = np.stack([nnls(shapes.T, wanted[j])[0] for j in range(5)], axis=1)
    w.setflags(write=False)
    return w


def vowel_shape_weights(z: np.ndarray) -> np.ndarray:
    """W (5, 5): column j the weights of the five vowel shapes (rows a i u e o) whose mouth
    comes nearest, on the default head, to the mouth Z's column j draws there - non-negative
    least squares over the displacements of every mouth vertex. Z (52, 5)."""
    return _shape_weights(np.ascontiguousarray(z, np.float64).tobytes())


def vowel_shapes(
    inp: DriveInput, params: VowelBlendParams, z: np.ndarray, w: np.ndarray | None = None
) -> BlendshapeTrack:
    """Z retargeted onto an avatar's five vowel shapes: Y = clip(G * X @ W.T), W from
    :func:`vowel_shape_weights` (pass it when driving many short tracks)."""
    w = vowel_shape_weights(z) if w is None else w
    y = np.clip(params.gain * inp.track.vowels() @ w.T, 0.0, 1.0)
    return BlendshapeTrack(
        inp.track.times, y, PRESET_NAMES,
        {"vowel_shape_weights": [[round(float(v), 4) for v in row] for row in w]},
    )  # fmt: skip


def _blend(track: VisemeTrack, gain: float, z_mat: np.ndarray) -> BlendshapeTrack:
    """Y (T, 52) = clip(G * X (T, 5) @ Z.T, 0, 1) on the track's times."""
    y = np.clip(gain * track.vowels() @ z_mat.T, 0.0, 1.0)
    return BlendshapeTrack(track.times, y, ARKIT_NAMES)


class VowelBlend(Method[VowelBlendParams]):
    """Y = clip(G * X @ Z.T) over the 52 ARKit targets."""

    spec = METHODS["vowel_blend"]
    live_problem = None

    def drive(self, inp: DriveInput, params: VowelBlendParams) -> BlendshapeTrack:
        return _blend(inp.track, params.gain, load_z(params.z, base_dir=inp.base_dir))

    def targets(self, params: VowelBlendParams, *, base_dir: Path = Path(".")) -> set[str]:
        """The ARKit rows its Z uses."""
        z = load_z(params.z, base_dir=base_dir)
        return {n for n, row in zip(ARKIT_NAMES, z, strict=True) if np.any(row > 0)}

    def input_files(self, params: VowelBlendParams) -> dict[str, str]:
        return {"z": params.z} if params.z.lower().endswith(".csv") else {}

    def input_problems(
        self, params: VowelBlendParams, *, base_dir: Path, where: tuple[str, ...] = ("params",)
    ) -> Iterator[tuple[tuple[str, ...], str]]:
        try:
            load_z(params.z, base_dir=base_dir)
        except FacelabError as exc:
            yield (*where, "z"), str(exc)

    def examples(self) -> tuple[VowelBlendParams, ...]:
        """Both shipped Z matrices."""
        return tuple(self.spec.parse({"z": z}) for z in BUILTIN_Z)

    def _stand_in(self, avatar: Avatar, params: VowelBlendParams, base_dir: Path) -> str | None:
        """Why the avatar's own vowel shapes must stand in for Z's ARKit targets (None when
        the ARKit mouth can show Z, or when the avatar has no usable vowel shapes)."""
        if not set(PRESET_NAMES) <= set(avatar.targets) or unusable_targets(avatar, PRESET_NAMES):
            return None
        missing = self.targets(params, base_dir=base_dir) - set(avatar.targets)
        if missing:
            return f"lacks {len(missing)} of the ARKit targets its Z uses"
        bad = unusable_targets(avatar, mouth_targets(load_z(params.z, base_dir=base_dir)))
        if bad:
            return (
                f"{len(bad)} of the ARKit mouth targets its Z drives cannot show it: "
                + "; ".join(f"{n} {why}" for n, why in sorted(bad.items())[:4])
                + (" …" if len(bad) > 4 else "")
            )
        return None

    def playback(
        self, avatar: Avatar, params: VowelBlendParams, *, base_dir: Path = Path(".")
    ) -> Playback:
        why = self._stand_in(avatar, params, base_dir)
        if why is not None:
            return Playback(
                True,
                "vowel shapes (the avatar's aa ih ou E oh, Z retargeted onto them: Y = G·W·X)",
                f"{avatar.source.get('kind')}: {why}; its vowel shapes aa ih ou E oh stand in, "
                "Z retargeted onto them (Y = G * W * X)",
            )
        playback = super().playback(avatar, params, base_dir=base_dir)
        if playback.playable:
            return Playback(True, "yes (the ARKit targets its Z uses)")
        return playback

    def driven_targets(
        self, avatar: Avatar, params: VowelBlendParams, *, base_dir: Path = Path(".")
    ) -> set[str]:
        if self._stand_in(avatar, params, base_dir) is not None:
            return set(PRESET_NAMES)
        return mouth_targets(load_z(params.z, base_dir=base_dir))

    def drive_on(
        self, avatar: Avatar, inp: DriveInput, params: VowelBlendParams
    ) -> BlendshapeTrack:
        return self.prepared(avatar, params, base_dir=inp.base_dir)(inp)

    def prepared(
        self, avatar: Avatar, params: VowelBlendParams, *, base_dir: Path
    ) -> Callable[[DriveInput], BlendshapeTrack]:
        """Whether the vowel shapes stand in and Z, decided and read once."""
        z_mat = load_z(params.z, base_dir=base_dir)
        if self._stand_in(avatar, params, base_dir) is not None:
            w = vowel_shape_weights(z_mat)
            return lambda inp: vowel_shapes(inp, params, z_mat, w)
        return lambda inp: _blend(inp.track, params.gain, z_mat)


register(VowelBlend())
