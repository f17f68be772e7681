"""Animation methods: viseme track (+ phoneme timing) -> blendshape track.

Each method is one function ``(DriveInput, params) -> BlendshapeTrack`` registered in
:data:`DRIVERS` under the name a protocol condition uses (``facelab.methods.METHODS`` holds
their parameter models). The vowel-driven method is

    Y (T, 52) = clip(G * X (T, 5) @ Z.T (5, 52), 0, 1)

with X the vowel intensities a, i, u, e, o per frame and Z (52, 5) a shipped or measured
matrix (column j: the ARKit coefficients of vowel j).
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.methods import (
    BUILTIN_Z,
    METHODS,
    TextVisemesParams,
    VisemeBaselineParams,
    VowelBlendParams,
)
from facelab.resources import package_file
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS
from facelab.stimuli.speech import Phone
from facelab.stimuli.visemes import VOWELS, VisemeTrack, from_phonemes

__all__ = ["DRIVERS", "BlendshapeTrack", "DriveInput", "drive", "load_z", "vowel_presets"]

DATA = package_file("facelab.stimuli", "data")


@dataclass(frozen=True)
class BlendshapeTrack:
    """times (T,) s; weights (T, K) in [0, 1]; names (K,) ARKit camelCase and/or viseme_*."""

    times: np.ndarray
    weights: np.ndarray
    names: tuple[str, ...]

    def column(self, name: str) -> np.ndarray:
        return self.weights[:, self.names.index(name)]


@dataclass(frozen=True)
class DriveInput:
    """What a method may use: the audio-analysed track (latency already removed), the phoneme
    timeline for TTS stimuli, and the folder custom files are relative to."""

    track: VisemeTrack
    phones: tuple[Phone, ...] = ()
    base_dir: Path = Path(".")


def load_z(z: str, *, base_dir: Path = Path(".")) -> np.ndarray:
    """A Z matrix (52, 5): a shipped name (standard, emphasized) or a CSV path with a
    ``blendshape`` column of ARKit names and columns a, i, u, e, o in [0, 1]."""
    path = DATA / f"z_{z}.csv" if z in BUILTIN_Z else base_dir / z
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise StageError(f"cannot read Z matrix {path}: {exc}") from None
    if not rows or set(rows[0]) != {"blendshape", *VOWELS}:
        raise StageError(f"{path}: expected columns blendshape, a, i, u, e, o")
    by_name = {r["blendshape"]: r for r in rows}
    missing = [n for n in ARKIT_NAMES if n not in by_name]
    unknown = [n for n in by_name if n not in ARKIT_NAMES]
    if missing or unknown:
        raise StageError(f"{path}: missing ARKit rows {missing[:5]} / unknown rows {unknown[:5]}")
    try:
        z_mat = np.array([[float(by_name[n][v]) for v in VOWELS] for n in ARKIT_NAMES])
    except ValueError as exc:
        raise StageError(f"{path}: non-numeric value ({exc})") from None
    if np.any(z_mat < 0) or np.any(z_mat > 1):
        raise StageError(f"{path}: values must lie in [0, 1]")
    return z_mat


def viseme_baseline(inp: DriveInput, params: VisemeBaselineParams) -> BlendshapeTrack:
    """The OVR LipSync path: the 15 viseme weights drive the ``viseme_*`` targets."""
    return BlendshapeTrack(
        inp.track.times, np.clip(params.gain * inp.track.weights, 0, 1), VISEME_TARGETS
    )


def vowel_blend(inp: DriveInput, params: VowelBlendParams) -> BlendshapeTrack:
    """Y = clip(G * X @ Z.T) over the 52 ARKit targets."""
    z_mat = load_z(params.z, base_dir=inp.base_dir)
    y = np.clip(params.gain * inp.track.vowels() @ z_mat.T, 0.0, 1.0)
    return BlendshapeTrack(inp.track.times, y, ARKIT_NAMES)


def vowel_presets(inp: DriveInput, params: VowelBlendParams) -> BlendshapeTrack:
    """The vowel-driven method on an avatar whose only mouth shapes are five vowel presets
    (VRM aa ih ou ee oh, loaded as viseme_aa … viseme_oh): Y = clip(G * X), the vowel
    intensities driving the presets directly - Z is not used."""
    y = np.clip(params.gain * inp.track.vowels(), 0.0, 1.0)
    names = ("viseme_aa", "viseme_ih", "viseme_ou", "viseme_E", "viseme_oh")  # a i u e o
    return BlendshapeTrack(inp.track.times, y, names)


def text_visemes(inp: DriveInput, params: TextVisemesParams) -> BlendshapeTrack:
    """Visemes from the phoneme timing (TTS stimuli), on the audio track's frame times."""
    if not inp.phones:
        raise StageError("method text_visemes needs a phoneme timeline (a text stimulus)")
    track = from_phonemes(
        inp.phones,
        fps=inp.track.fps,
        smoothing_s=params.smoothing_s,
        duration_s=float(inp.track.times[-1]),
    )
    return BlendshapeTrack(track.times, np.clip(params.gain * track.weights, 0, 1), VISEME_TARGETS)


DRIVERS: dict[str, Callable[[DriveInput, object], BlendshapeTrack]] = {
    "viseme_baseline": viseme_baseline,  # type: ignore[dict-item]
    "vowel_blend": vowel_blend,  # type: ignore[dict-item]
    "text_visemes": text_visemes,  # type: ignore[dict-item]
}
assert set(DRIVERS) == set(METHODS), "every registered method needs a driver"


def drive(method: str, inp: DriveInput, params: dict) -> BlendshapeTrack:
    """Run a registered method with parameters as written in a protocol."""
    if method not in METHODS:
        raise StageError(f"unknown method {method!r}; registered: {', '.join(METHODS)}")
    return DRIVERS[method](inp, METHODS[method].params.model_validate(params))
