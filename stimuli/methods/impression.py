"""Seed 001 as a protocol method: an expression moved along a learned impression direction to
level q, eased from neutral and back, optionally with vowel-driven speech on top."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from facelab.errors import FacelabError, StageError
from facelab.methods import METHODS, ImpressionParams
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.impression.model import ImpressionModel, envelope_at
from facelab.stimuli.methods.registry import Method, Playback, register
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput
from facelab.stimuli.methods.vowel_blend import VowelBlend

__all__ = ["Impression"]


class Impression(Method):
    """X(t) = e(t)·ŝ_clipped on the track's frame times (the avatar's rest face is the
    neutral), e the lead/onset/hold/offset envelope (hold omitted: until the offset ends with
    the stimulus); optionally plus the vowel-driven speech track, clipped to [0, 1]."""

    spec = METHODS["impression"]

    def drive(self, inp: DriveInput, params: ImpressionParams) -> BlendshapeTrack:  # type: ignore[override]
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
            faces = np.clip(faces + VowelBlend().drive(inp, params.speech).weights, 0.0, 1.0)
        notes = {**info, "model_sha256": model.data_sha256, "speech": params.speech is not None}
        moving = np.nonzero(np.any(faces > 0, axis=0))[0]  # only the channels used: avatars
        names = tuple(ARKIT_NAMES[j] for j in moving)  # may lack the others
        return BlendshapeTrack(times, faces[:, moving], names, notes)

    def input_files(self, params: ImpressionParams) -> dict[str, str]:  # type: ignore[override]
        files = {"model": params.model}
        if params.speech is not None:
            files.update(VowelBlend().input_files(params.speech))
        return files

    def input_problems(  # type: ignore[override]
        self, params: ImpressionParams, *, base_dir: Path
    ) -> Iterator[tuple[tuple[str, ...], str]]:
        try:  # the whole model, as rendering loads it (its header and expression are
            ImpressionModel.load(base_dir / params.model)  # checked with the protocol)
        except FacelabError as exc:
            yield ("params", "model"), str(exc)
        if params.speech is not None:
            yield from VowelBlend().input_problems(
                params.speech, base_dir=base_dir, where=("params", "speech")
            )

    def playback(self, avatar: Avatar, params: object, *, base_dir: Path = Path(".")) -> Playback:
        n = len(set(avatar.targets) & set(ARKIT_NAMES))
        return Playback(True, f"plays the ARKit targets its model moves ({n}/52 on this avatar)")


register(Impression())
