"""The viseme methods: 15 viseme weights drive the 14 ``viseme_*`` targets, from the audio
analyser (``viseme_baseline``, the OVR LipSync path) or from phoneme timing (``text_visemes``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.methods import METHODS, TextVisemesParams, VisemeBaselineParams
from facelab.stimuli.arkit import VISEME_TARGETS
from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.avatar.targets import VISEME_MIXES, vowel_presets_only
from facelab.stimuli.methods.registry import Method, P, Playback, register
from facelab.stimuli.methods.types import BlendshapeTrack, DriveInput
from facelab.stimuli.speech.track import from_phonemes

__all__ = ["TextVisemes", "VisemeBaseline"]


class _VisemeMethod(Method[P]):
    uses_visemes = True

    def targets(self, params: P, *, base_dir: Path = Path(".")) -> set[str]:
        return set(VISEME_TARGETS[1:])

    def driven_targets(self, avatar: Avatar, params: P, *, base_dir: Path = Path(".")) -> set[str]:
        """The viseme shapes it moves, less those a VRM gets as zero shapes (said by
        :meth:`playback`'s stand-in note instead)."""
        zero = set(avatar.source.get("zero_visemes") or ())
        if vowel_presets_only(avatar):
            zero |= set(self.targets(params)) - set(avatar.targets)
        return (self.targets(params) & set(avatar.targets)) - zero

    def playback(self, avatar: Avatar, params: P, *, base_dir: Path = Path(".")) -> Playback:
        have = set(avatar.targets)
        kind = avatar.source.get("kind")
        zero = avatar.source.get("zero_visemes")
        if zero:  # an avatar given zero shapes by with_viseme_mixes
            note = f"{kind}: no shape for {' '.join(zero)} (vowel presets only)"
            return Playback(True, "vowel presets only (the consonant visemes get no shape)", note)
        visemes = self.targets(params)
        if visemes <= have:
            return Playback(True, "yes (viseme_* targets)")
        if vowel_presets_only(avatar):
            missing = " ".join(sorted(visemes - have))
            return Playback(
                True,
                "vowel presets only (the consonant visemes get no shape)",
                f"{kind}: no shape for {missing} (vowel presets only)",
            )
        absent = sorted(visemes - have)
        lacking = sorted({n for v in absent for n in VISEME_MIXES[v]} - have)
        if not lacking:
            return Playback(True, "via ARKit mixes (viseme_* built from ARKit shapes)")
        return Playback(
            False,
            f"no: lacks {', '.join(absent[:4])}…",
            problem=f"avatar {avatar.name!r} lacks targets for method {self.name!r}: "
            f"{', '.join(absent)} (and the ARKit shapes to build them: {', '.join(lacking)})",
        )


class VisemeBaseline(_VisemeMethod[VisemeBaselineParams]):
    """The OVR LipSync path: the 15 viseme weights drive the ``viseme_*`` targets."""

    spec = METHODS["viseme_baseline"]
    live_problem = None

    def drive(self, inp: DriveInput, params: VisemeBaselineParams) -> BlendshapeTrack:
        return BlendshapeTrack(
            inp.track.times, np.clip(params.gain * inp.track.weights, 0, 1), VISEME_TARGETS
        )


class TextVisemes(_VisemeMethod[TextVisemesParams]):
    """Visemes from the phoneme timing (TTS stimuli), on the audio track's frame times."""

    spec = METHODS["text_visemes"]
    live_problem = "it needs the words' phoneme timing, which live speech does not come with"

    def drive(self, inp: DriveInput, params: TextVisemesParams) -> BlendshapeTrack:
        if not inp.phones:
            raise StageError("method text_visemes needs a phoneme timeline (a text stimulus)")
        track = from_phonemes(
            inp.phones,
            fps=inp.track.fps,
            smoothing_s=params.smoothing_s,
            duration_s=float(inp.track.times[-1]),
        )
        weights = np.clip(params.gain * track.weights, 0, 1)
        return BlendshapeTrack(track.times, weights, VISEME_TARGETS)


register(VisemeBaseline())
register(TextVisemes())
