"""The registry of animation methods a protocol condition can name.

Each entry declares the method's parameters as a typed model (unknown keys are errors) and
what the method needs from an avatar. A new method is one parameter model plus one entry in
:data:`METHODS`; its drive function is registered beside it in ``facelab.stimuli.drive``.

This module is pure data: it imports nothing heavy, so the protocol loader can validate
conditions without the audio or rendering stacks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "BUILTIN_Z",
    "METHODS",
    "ImpressionParams",
    "MethodSpec",
    "TextVisemesParams",
    "VisemeBaselineParams",
    "VowelBlendParams",
]

#: Z matrices shipped with facelab (52 ARKit rows x 5 vowel columns), by name.
BUILTIN_Z: tuple[str, ...] = ("standard", "emphasized")


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class VisemeBaselineParams(_Params):
    """The OVR-LipSync path: 15 viseme weights drive the 14 ``viseme_*`` targets."""

    gain: float = Field(
        1.0, gt=0, le=4, description="Multiplier on viseme weights before clipping to [0, 1]."
    )


class VowelBlendParams(_Params):
    """The vowel-driven blendshape method Y = G * Z * X (52 ARKit coefficients)."""

    z: str = Field(
        "standard",
        description="A shipped Z matrix (standard, emphasized) or a path to a 52x5 CSV "
        "relative to the protocol file.",
    )
    gain: float = Field(1.0, gt=0, le=4, description="The gain G; Y is clipped to [0, 1].")


class TextVisemesParams(_Params):
    """Visemes from OpenJTalk phoneme timing instead of audio analysis (TTS stimuli only)."""

    gain: float = Field(1.0, gt=0, le=4, description="Multiplier on viseme weights.")
    smoothing_s: float = Field(
        0.04, ge=0, le=0.5, description="Coarticulation smoothing time constant in seconds."
    )


class ImpressionParams(_Params):
    """Seed 001: an expression edited along a learned impression direction, level ``q``."""

    model: str = Field(description="An impression model (facelab impression fit), relative to "
                       "the protocol file.")  # fmt: skip
    expression: str = Field(description="The model's expression to show, e.g. open_smile.")
    q: float = Field(ge=-5, le=5, description="The level q_c: f + q·δ·w (eq. 2).")
    ease: Literal["sigmoid", "linear", "smoothstep"] = "sigmoid"
    k: float = Field(5.0, gt=0, le=50, description="Sigmoid steepness (eq. 4).")
    lead_s: float = Field(0.3, ge=0, le=10, description="Neutral before the onset (s).")
    onset_s: float = Field(0.6, ge=0, le=10, description="Neutral -> expression (s).")
    hold_s: float | None = Field(
        None, ge=0, le=60, description="Expression held (s); omitted: until the offset ends "
        "with the stimulus.",
    )  # fmt: skip
    offset_s: float = Field(0.6, ge=0, le=10, description="Expression -> neutral (s).")
    speech: VowelBlendParams | None = Field(
        None, description="Also lip-sync the stimulus's speech with the vowel-driven method "
        "(added to the expression, clipped to [0, 1]); omitted: no speech animation.",
    )  # fmt: skip


@dataclass(frozen=True)
class MethodSpec:
    """What the protocol layer needs to know about one animation method."""

    name: str
    params: type[_Params]
    summary: str
    needs_text: bool = False  # True when the method needs the stimulus text (phoneme timing)


METHODS: dict[str, MethodSpec] = {
    spec.name: spec
    for spec in (
        MethodSpec(
            "viseme_baseline",
            VisemeBaselineParams,
            "15 audio-analysed viseme weights drive the 14 viseme_* targets (OVR LipSync path)",
        ),
        MethodSpec(
            "vowel_blend",
            VowelBlendParams,
            "Y = G*Z*X: 5 vowel intensities through a 52x5 Z matrix to the ARKit targets",
        ),
        MethodSpec(
            "text_visemes",
            TextVisemesParams,
            "visemes from OpenJTalk phoneme timing, with coarticulation smoothing",
            needs_text=True,
        ),
        MethodSpec(
            "impression",
            ImpressionParams,
            "seed 001: an expression moved along a learned impression direction to level q, "
            "eased from neutral and back (optionally with vowel-driven speech on top)",
        ),
    )
}
