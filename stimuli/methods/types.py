"""Animation methods: viseme track (+ phoneme timing) -> blendshape track.

Each method is one function ``(DriveInput, params) -> BlendshapeTrack`` registered in
:data:`DRIVERS` under the name a protocol condition uses (``facelab.methods.METHODS`` holds
their parameter models). The vowel-driven method is

    Y (T, 52) = clip(G * X (T, 5) @ Z.T (5, 52), 0, 1)

with X the vowel intensities a, i, u, e, o per frame and Z (52, 5) a shipped or measured
matrix (column j: the ARKit coefficients of vowel j).
"""

from __future__ import annotations

from collections.abc import Container
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facelab.stimuli.speech.audio import Phone, Speech
from facelab.stimuli.speech.track import VisemeTrack

__all__ = ["BlendshapeTrack", "DriveInput"]


@dataclass(frozen=True)
class BlendshapeTrack:
    """times (T,) s; weights (T, K) in [0, 1]; names (K,) ARKit camelCase and/or viseme_*."""

    times: np.ndarray
    weights: np.ndarray
    names: tuple[str, ...]
    notes: dict = field(default_factory=dict, compare=False)  # facts for the clip's JSON
    #: head and eye angles (T, 5) in degrees on ``times``: yaw, pitch, roll, eye yaw, eye pitch
    #: (signs as :mod:`facelab.stimuli.avatar.rig`), for a method whose source turns the head
    #: (a capture); None: the head is left to the behaviour layer
    poses: np.ndarray | None = field(default=None, compare=False)

    def column(self, name: str) -> np.ndarray:
        return self.weights[:, self.names.index(name)]

    def moved_but_missing(self, targets: Container[str]) -> list[str]:
        """The channels not in ``targets`` (an avatar's) that this track moves: a channel
        held at 0 throughout (an ARKit export without ``tongueOut`` playing a Z matrix whose
        ``tongueOut`` row is 0) may be missing, one the track moves may not."""
        return [n for j, n in enumerate(self.names)
                if n not in targets and np.any(self.weights[:, j] != 0)]  # fmt: skip


@dataclass(frozen=True)
class DriveInput:
    """What a method may use: the audio-analysed track (latency already removed), the phoneme
    timeline for TTS stimuli, the folder custom files are relative to, which stimulus the clip
    shows (set and id: a method reading one file per stimulus) and its audio."""

    track: VisemeTrack
    phones: tuple[Phone, ...] = ()
    base_dir: Path = Path(".")
    stimulus_set: str = ""
    stimulus_id: str = ""
    audio: Speech | None = None
