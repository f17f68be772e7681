"""Animation methods: viseme track (+ phoneme timing) -> blendshape track.

Each method is one function ``(DriveInput, params) -> BlendshapeTrack`` registered in
:data:`DRIVERS` under the name a protocol condition uses (``facelab.methods.METHODS`` holds
their parameter models). The vowel-driven method is

    Y (T, 52) = clip(G * X (T, 5) @ Z.T (5, 52), 0, 1)

with X the vowel intensities a, i, u, e, o per frame and Z (52, 5) a shipped or measured
matrix (column j: the ARKit coefficients of vowel j).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.methods import (
    METHODS,
    ImpressionParams,
    TextVisemesParams,
    VisemeBaselineParams,
    VowelBlendParams,
)
from facelab.stimuli.arkit import ARKIT_NAMES, VISEME_TARGETS
from facelab.stimuli.impression import ImpressionModel, envelope_at
from facelab.stimuli.speech import Phone
from facelab.stimuli.visemes import VisemeTrack, from_phonemes
from facelab.stimuli.zmatrix import load_z

__all__ = ["DRIVERS", "BlendshapeTrack", "DriveInput", "drive", "load_z", "vowel_presets"]


@dataclass(frozen=True)
class BlendshapeTrack:
    """times (T,) s; weights (T, K) in [0, 1]; names (K,) ARKit camelCase and/or viseme_*."""

    times: np.ndarray
    weights: np.ndarray
    names: tuple[str, ...]
    notes: dict = field(default_factory=dict, compare=False)  # facts for the clip's JSON

    def column(self, name: str) -> np.ndarray:
        return self.weights[:, self.names.index(name)]


@dataclass(frozen=True)
class DriveInput:
    """What a method may use: the audio-analysed track (latency already removed), the phoneme
    timeline for TTS stimuli, and the folder custom files are relative to."""

    track: VisemeTrack
    phones: tuple[Phone, ...] = ()
    base_dir: Path = Path(".")


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


def impression(inp: DriveInput, params: ImpressionParams) -> BlendshapeTrack:
    """Seed 001 on the track's frame times: X(t) = e(t)·ŝ_clipped (the avatar's rest face is the
    neutral), with e the lead/onset/hold/offset envelope (hold omitted: until the offset ends
    with the stimulus); optionally plus the vowel-driven speech track, clipped to [0, 1]."""
    model = ImpressionModel.load_cached(inp.base_dir / params.model)
    if model.space != "arkit":
        raise StageError(f"{params.model}: conditions need an ARKit-space impression model")
    times = inp.track.times
    duration = float(times[-1]) if len(times) else 0.0
    hold = params.hold_s
    if hold is None:
        hold = max(0.0, duration - params.lead_s - params.onset_s - params.offset_s)
    env = envelope_at(
        times, onset_s=params.onset_s, hold_s=hold, offset_s=params.offset_s,
        lead_s=params.lead_s, kind=params.ease, k=params.k,
    )  # fmt: skip
    faces, info = model.frames(params.expression, params.q, env, neutral=np.zeros(52))
    if params.speech is not None:
        faces = np.clip(faces + vowel_blend(inp, params.speech).weights, 0.0, 1.0)
    notes = {**info, "model_sha256": model.data_sha256, "speech": params.speech is not None}
    moving = np.nonzero(np.any(faces > 0, axis=0))[0]  # only the channels used: avatars may
    names = tuple(ARKIT_NAMES[j] for j in moving)  # lack the others
    return BlendshapeTrack(times, faces[:, moving], names, notes)


DRIVERS: dict[str, Callable[[DriveInput, object], BlendshapeTrack]] = {
    "viseme_baseline": viseme_baseline,  # type: ignore[dict-item]
    "vowel_blend": vowel_blend,  # type: ignore[dict-item]
    "text_visemes": text_visemes,  # type: ignore[dict-item]
    "impression": impression,  # type: ignore[dict-item]
}
assert set(DRIVERS) == set(METHODS), "every registered method needs a driver"


def drive(method: str, inp: DriveInput, params: dict) -> BlendshapeTrack:
    """Run a registered method with parameters as written in a protocol."""
    if method not in METHODS:
        raise StageError(f"unknown method {method!r}; registered: {', '.join(METHODS)}")
    return DRIVERS[method](inp, METHODS[method].params.model_validate(params))
