"""The registry of animation methods a protocol condition can name.

Each :class:`MethodSpec` is the protocol half of a method: its parameters as a typed model
(unknown keys are errors), a summary, whether it needs the stimulus text, and the checks of
the files its parameters name. The stimulus half (drive, targets, playability) is the method's
``facelab.stimuli.methods.Method``, whose ``register`` puts the spec here too: a plugin method
is one object registered once. The built-in specs are declared here so that protocols validate
without the audio or rendering stacks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from facelab.formats import impression_header_problems

__all__ = [
    "BUILTIN_METHODS",
    "BUILTIN_Z",
    "METHODS",
    "ExternalTrackParams",
    "ImpressionParams",
    "MethodSpec",
    "Params",
    "TextVisemesParams",
    "VisemeBaselineParams",
    "VowelBlendParams",
    "load_plugin_specs",
    "method_spec",
    "register_spec",
]

#: Z matrices shipped with facelab (52 ARKit rows x 5 vowel columns), by name.
BUILTIN_Z: tuple[str, ...] = ("standard", "emphasized")


class _Params(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


#: the base of a method's parameter model (unknown keys are errors, values frozen): a plugin
#: method's parameters subclass it
Params = _Params


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


class ExternalTrackParams(_Params):
    """An animation made elsewhere (a capture, another model), one file per stimulus."""

    tracks: str = Field(description="A folder relative to the protocol file holding "
                        "<stimulus_set>/<stimulus_id>.<csv|json|glb|gltf>.")  # fmt: skip
    format: Literal["auto", "live_link_face", "arkit_json", "audio2face", "viseme_csv",
                    "gltf"] = Field("auto", description="The files' format; auto tells them "
                                    "apart by extension and content.")  # fmt: skip
    offset_ms: float | Literal["auto"] = Field(
        0.0, description="Shift of the animation against the stimulus audio (ms, positive: "
        "later); auto aligns each file by the WAV recorded with it (<stimulus_id>.wav).",
    )  # fmt: skip
    fps: float | None = Field(
        None, gt=0, le=1000, description="The timecode's frame rate of a Live Link Face "
        "capture, where the file cannot tell it (a capture shorter than a second).",
    )  # fmt: skip
    head: bool = Field(
        True, description="Play a Live Link Face capture's head and eye angles on the avatar's "
        "head, neck and eye joints (a condition with a behaviour layer keeps that layer's "
        "head); false: the head stays still.",
    )  # fmt: skip
    angle_unit: Literal["radians", "degrees"] = Field(
        "radians", description="The unit of the capture's head and eye angles.",
    )  # fmt: skip


#: A problem found by a method's protocol check: (key path under the condition, message).
Problem = tuple[tuple[str | int, ...], str]


def _z_problems(z: str, base_dir: Path, where: tuple[str | int, ...]) -> Iterator[Problem]:
    """A Z parameter names a shipped matrix or an existing CSV file."""
    if z in BUILTIN_Z:
        return
    z_path = base_dir / z
    if z_path.suffix.lower() != ".csv" or not z_path.is_file():
        found = ("is a folder" if z_path.is_dir() else "is not a .csv file"
                 if z_path.exists() else "was not found")  # fmt: skip
        yield (
            where,
            f"expected one of {', '.join(BUILTIN_Z)} or an existing .csv file "
            f"(52 rows x 5 vowels); {z_path} {found}",
        )


def _vowel_blend_checks(params: VowelBlendParams, base_dir: Path) -> Iterator[Problem]:
    yield from _z_problems(params.z, base_dir, ("params", "z"))


def _impression_checks(params: ImpressionParams, base_dir: Path) -> Iterator[Problem]:
    for key, message in impression_header_problems(
        base_dir / params.model, expression=params.expression, space="arkit"
    ):
        yield ("params", key), message
    if params.speech is not None:
        yield from _z_problems(params.speech.z, base_dir, ("params", "speech", "z"))


@dataclass(frozen=True)
class MethodSpec:
    """What the protocol layer needs to know about one animation method.

    checks : ``(params, base_dir) -> (key path, message)…`` for the files the parameters name
        (paths relative to the protocol's folder); the key path is under the condition.
    """

    name: str
    params: type[_Params]
    summary: str
    needs_text: bool = False  # True when the method needs the stimulus text (phoneme timing)
    checks: Callable[[Any, Path], Iterator[Problem]] | None = None

    def parse(self, params: Mapping[str, Any] | BaseModel | None) -> Any:
        """The typed parameters (a model instance passes through)."""
        if isinstance(params, self.params):
            return params
        return self.params.model_validate(dict(params or {}))

    def problems(self, params: Any, base_dir: Path) -> Iterator[Problem]:
        """The method's own protocol checks on validated ``params``."""
        if self.checks is not None:
            yield from self.checks(params, base_dir)


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
            checks=_vowel_blend_checks,
        ),
        MethodSpec(
            "text_visemes",
            TextVisemesParams,
            "visemes from OpenJTalk phoneme timing, with coarticulation smoothing",
            needs_text=True,
        ),
        MethodSpec(
            "external_track",
            ExternalTrackParams,
            "an animation made elsewhere (Live Link Face, Audio2Face-3D, Oculus/uLipSync "
            "visemes, ARKit JSON, a glTF animation), one file per stimulus, resampled to the "
            "clip",
        ),
        MethodSpec(
            "impression",
            ImpressionParams,
            "seed 001: an expression moved along a learned impression direction to level q, "
            "eased from neutral and back (optionally with vowel-driven speech on top)",
            checks=_impression_checks,
        ),
    )
}


#: the methods facelab ships (plugins add to METHODS, never to this)
BUILTIN_METHODS: tuple[str, ...] = tuple(METHODS)


def method_spec(name: str) -> MethodSpec | None:
    """The spec of method ``name``; a name facelab does not know first loads the installed
    plugins' specs (entry-point group ``facelab.methods``)."""
    if name not in METHODS:
        load_plugin_specs()
    return METHODS.get(name)


def load_plugin_specs() -> None:
    """Register the protocol specs of the installed method plugins (each entry point names a
    ``Method`` subclass whose ``spec`` is a :class:`MethodSpec`); a plugin that fails to load
    is left to ``facelab plugins`` to report."""
    from facelab.plugins import GROUPS, loaded

    for entry in loaded(GROUPS["methods"]):
        spec = getattr(entry.obj, "spec", None)
        if isinstance(spec, MethodSpec) and spec.name == entry.name and spec.name not in METHODS:
            register_spec(spec)


def register_spec(spec: MethodSpec) -> None:
    """Add a plugin method's protocol spec (``facelab.stimuli.methods.register`` calls this)."""
    if METHODS.get(spec.name, spec) is not spec:
        raise ValueError(f"method {spec.name!r} is registered already")
    METHODS[spec.name] = spec
