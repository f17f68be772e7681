"""Seed 001 as a protocol method: an expression moved along a learned impression direction to
level q, eased from neutral and back, optionally with vowel-driven speech on top."""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from facelab.errors import FacelabError, StageError
from facelab.methods import METHODS, ImpressionParams
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.impression.model import VISIBLE_CHANGE, ImpressionModel, envelope_at
from facelab.stimuli.methods.registry import Method, Playback, register
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput
from facelab.stimuli.methods.vowel_blend import VowelBlend

__all__ = ["Impression"]


class Impression(Method[ImpressionParams]):
    """X(t) = e(t)·ŝ_clipped on the track's frame times (the avatar's rest face is the
    neutral), e the lead/onset/hold/offset envelope (hold omitted: until the offset ends with
    the stimulus); optionally plus the vowel-driven speech track, clipped to [0, 1]."""

    spec = METHODS["impression"]
    live_problem = "its expression's onset, hold and offset are timed against the whole clip"

    def drive(self, inp: DriveInput, params: ImpressionParams) -> BlendshapeTrack:
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

    def input_files(self, params: ImpressionParams) -> dict[str, str]:
        files = {"model": params.model}
        if params.speech is not None:
            files.update(VowelBlend().input_files(params.speech))
        return files

    def input_problems(
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

    def protocol_notes(
        self, settings: Sequence[ImpressionParams], *, base_dir: Path, has_tasks: bool
    ) -> list[str]:
        """One line per pair of neighbouring levels (same model and expression) whose faces
        differ by less than :data:`VISIBLE_CHANGE` in the channel that moves most. With
        forced-choice or identification tasks only the lowest and highest levels are asked to
        differ visibly: close levels are what a psychometric design wants."""
        levels: dict[tuple[str, str], set[float]] = {}
        for params in settings:
            levels.setdefault((params.model, params.expression), set()).add(float(params.q))
        notes = []
        for (model_file, expression), qs in levels.items():
            model = ImpressionModel.load_cached(base_dir / model_file)
            limit = VISIBLE_CHANGE[model.space]
            unit = "" if model.space == "arkit" else " m"
            ordered = sorted(qs)
            ends = [(ordered[0], ordered[-1])] if len(ordered) > 1 else []
            for lo, hi in ends if has_tasks else itertools.pairwise(ordered):
                neutral = np.zeros_like(model.neutral_mean) if model.space == "arkit" else None
                change, where = model.level_change(expression, hi, q_from=lo, neutral=neutral)
                if change < limit:
                    notes.append(
                        f"warning: {model_file} {expression}: levels q={lo:g} and q={hi:g} "
                        f"differ by {change:.3f}{unit} at most ({where}), below the "
                        f"{limit:g}{unit} taken as visible; raise the levels or refit with "
                        "'facelab impression fit --step'"
                    )
        return notes

    def playback(
        self, avatar: Avatar, params: ImpressionParams, *, base_dir: Path = Path(".")
    ) -> Playback:
        n = len(set(avatar.targets) & set(ARKIT_NAMES))
        return Playback(True, f"plays the ARKit targets its model moves ({n}/52 on this avatar)")


register(Impression())
