"""Behaviour units (seed 003, EMBOS) for a talking head: the library file and its rules.

A *unit* is one non-verbal behaviour of one layer:

* ``posture`` - slow, held head/neck orientation and baseline expression (seconds);
* ``mannerism`` - gaze aversions, squints, brow furrows, lip-corner presses … (EMBOS しぐさ);
* ``gesture`` - nods, shakes, brow raises tied to words and accents (EMBOS ジェスチャ);
* ``blink`` - blinks. EMBOS has three layers; blinks are kept in a fourth, autonomous network
  so that "one unit per layer at a time" (eq. 1) never suppresses them during a gaze aversion
  (blinks co-occur with gaze shifts in people, and their rate is what viewers notice).

Each unit names the **channels** it drives with their amplitude at curve value 1: ARKit
blendshape names (weights) and the rotations ``neck_yaw neck_pitch neck_roll`` (postures),
``head_yaw head_pitch head_roll`` (gestures), ``eye_yaw eye_pitch`` (degrees; signs as in
:mod:`facelab.stimuli.avatar.rig`: yaw + = the avatar's left, pitch + = down). Speech owns the
articulation channels: a unit may not write ``jaw*``, ``tongue*`` or ``mouth*`` except the
corner channels ``mouthSmile*``, ``mouthFrown*`` and ``mouthDimple*`` (which add to speech).

The **curve** is a list of ``[phase, value]`` keys over the unit's duration (phase 0..1,
smoothstep between keys) with BML sync points (``start ready stroke_start stroke stroke_end
relax end``) as phases; a triggered gesture is placed so that its ``stroke`` falls on the
trigger. Per emotion the unit has an intensity (eq. 2), a duration L_d and a wait L_w (eq. 3),
and postures may have a pose per emotion; values for a mixed emotion are blended by eq. 5.

A library file is JSON or YAML: ``{"units": [...], "continuity": {...}, ...}`` - exactly the
shape ``facelab behaviour fit`` writes, plus the motion fields (channels, curve, triggers).
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from facelab.emotions import EMOTIONS
from facelab.errors import BehaviourError
from facelab.protocol_checks import pydantic_message
from facelab.protocol_yaml import read_data
from facelab.resources import package_file
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.textfiles import read_text

__all__ = [
    "EMOTIONS",
    "LAYERS",
    "ROTATIONS",
    "SYNC_POINTS",
    "Curve",
    "Library",
    "Triggers",
    "Unit",
    "default_library",
    "is_speech_channel",
    "load_library",
]

#: Networks, upper to lower (eq. 1's M_u of a layer is every layer before it).
LAYERS: tuple[str, ...] = ("posture", "mannerism", "gesture", "blink")
#: Rotation channels in degrees; the neck carries postures, the head gestures.
ROTATIONS: tuple[str, ...] = (
    "neck_yaw",
    "neck_pitch",
    "neck_roll",
    "head_yaw",
    "head_pitch",
    "head_roll",
    "eye_yaw",
    "eye_pitch",
)
#: BML 1.0 sync points, in the order their phases must follow.
SYNC_POINTS: tuple[str, ...] = (
    "start",
    "ready",
    "stroke_start",
    "stroke",
    "stroke_end",
    "relax",
    "end",
)
PROSODIC_TRIGGERS = ("accent", "phrase_end", "utterance_start", "pause")
_CORNERS = re.compile(r"^mouth(Smile|Frown|Dimple)(Left|Right)$")
_MIRRORED = {"neck_yaw", "neck_roll", "head_yaw", "head_roll", "eye_yaw"}


def is_speech_channel(name: str) -> bool:
    """True for the articulation channels speech owns (``jaw* tongue* mouth*`` but corners)."""
    return name.startswith(("jaw", "tongue", "mouth")) and not _CORNERS.match(name)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _check_emotions(value: dict[str, float], what: str) -> dict[str, float]:
    unknown = sorted(set(value) - set(EMOTIONS))
    if unknown:
        raise ValueError(
            f"{what}: unknown emotion(s) {', '.join(unknown)}; use {', '.join(EMOTIONS)}"
        )
    return value


class Curve(_Model):
    """Keys ``[[phase, value], …]`` (phase 0..1 rising, value -1..1) and sync-point phases."""

    keys: list[tuple[float, float]] = Field(min_length=2)
    sync: dict[str, float] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _valid(self) -> Curve:
        phases = [k[0] for k in self.keys]
        if phases[0] != 0 or phases[-1] != 1 or any(b <= a for a, b in itertools.pairwise(phases)):
            raise ValueError("curve keys need rising phases from 0 to 1")
        if any(abs(k[1]) > 1 for k in self.keys):
            raise ValueError("curve values must lie in [-1, 1] (amplitudes go in 'channels')")
        unknown = sorted(set(self.sync) - set(SYNC_POINTS))
        if unknown:
            raise ValueError(
                f"unknown sync point(s) {', '.join(unknown)}; BML has {', '.join(SYNC_POINTS)}"
            )
        order = [self.sync[s] for s in SYNC_POINTS if s in self.sync]
        if any(not 0 <= p <= 1 for p in order) or any(b < a for a, b in itertools.pairwise(order)):
            raise ValueError("sync points must lie in [0, 1] in BML order (start … end)")
        return self

    def phase(self, name: str) -> float:
        """The phase of a sync point (start 0, end 1, stroke: the largest |value| key)."""
        if name in self.sync:
            return self.sync[name]
        if name == "start":
            return 0.0
        if name == "end":
            return 1.0
        if name == "stroke":
            return max(self.keys, key=lambda k: abs(k[1]))[0]
        raise BehaviourError(f"curve has no sync point {name!r}")


class Triggers(_Model):
    """What places a gesture (or makes a mannerism likelier): words and prosodic events.

    ``mode: require`` - φ_state × 1 at a trigger, × ``min_gain`` elsewhere (gestures);
    ``mode: boost`` - × ``gain`` at a trigger, × 1 elsewhere."""

    words: list[str] = Field(default_factory=list, description="Substrings of a word's surface.")
    prosody: list[Literal["accent", "phrase_end", "utterance_start", "pause"]] = Field(
        default_factory=list
    )
    mode: Literal["require", "boost"] = "require"
    gain: float = Field(3.0, ge=1, le=100)
    min_gain: float = Field(0.1, ge=0, le=1)


class Unit(_Model):
    """One behaviour unit (see the module docstring)."""

    behaviour: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9_\-]*$")
    layer: Literal["posture", "mannerism", "gesture", "blink"]
    intensity: dict[str, float] = Field(description="Eq. 2 intensity per emotion, 0..1.")
    duration_s: dict[str, float] = Field(description="L_d per emotion (s).")
    wait_s: dict[str, float] = Field(description="L_w per emotion (s).")
    channels: dict[str, float] = Field(
        default_factory=dict, description="Channel -> amplitude at curve value 1."
    )
    pose_by_emotion: dict[str, dict[str, float]] = Field(
        default_factory=dict, description="Per-emotion amplitudes (postures; blended by eq. 5)."
    )
    curve: Curve | None = None
    triggers: Triggers | None = None
    wait_cv: float = Field(0.0, ge=0, le=3, description="Log-normal spread of each wait.")
    speaking_wait_factor: float = Field(
        1.0, gt=0, le=5, description="Waits while the avatar speaks are multiplied by this."
    )
    mirror: bool = Field(False, description="Flip yaw/roll signs at random per occurrence.")
    bml: dict[str, str] = Field(
        default_factory=dict,
        description="BML 1.0 element for export, e.g. {tag: head, lexeme: NOD}.",
    )
    source: str = ""
    observed: dict[str, dict[str, float]] = Field(
        default_factory=dict, description="Statistics from annotations (facelab behaviour fit)."
    )

    @field_validator("intensity", "duration_s", "wait_s")
    @classmethod
    def _emotions(cls, v: dict[str, float], info) -> dict[str, float]:
        _check_emotions(v, info.field_name)
        if any(x < 0 for x in v.values()):
            raise ValueError(f"{info.field_name}: values must be >= 0")
        if info.field_name == "intensity" and any(x > 1 for x in v.values()):
            raise ValueError("intensity values must lie in [0, 1]")
        return v

    @model_validator(mode="after")
    def _channels(self) -> Unit:
        names = set(self.channels) | {c for pose in self.pose_by_emotion.values() for c in pose}
        _check_emotions(self.pose_by_emotion, "pose_by_emotion")
        for name in sorted(names):
            if is_speech_channel(name):
                raise ValueError(
                    f"channel {name!r} belongs to speech articulation (jaw*, tongue*, mouth* "
                    "except mouthSmile*, mouthFrown*, mouthDimple*): a behaviour may not write it"
                )
            if name not in ARKIT_NAMES and name not in ROTATIONS:
                raise ValueError(
                    f"unknown channel {name!r}: use ARKit names or {', '.join(ROTATIONS)}"
                )
        if names and self.curve is None:
            raise ValueError("a unit with channels needs a 'curve'")
        if not self.duration_s or not self.wait_s:
            raise ValueError("a unit needs duration_s and wait_s for at least one emotion")
        return self

    @property
    def has_motion(self) -> bool:
        return bool(self.channels or self.pose_by_emotion) and self.curve is not None

    def channel_names(self) -> frozenset[str]:
        """Every channel the unit may drive (eq. 1's ω_l compares these)."""
        return frozenset(self.channels) | {c for p in self.pose_by_emotion.values() for c in p}

    @staticmethod
    def mirrored(name: str) -> bool:
        return name in _MIRRORED


class Library(_Model):
    """A behaviour library: units plus the planner's constants."""

    units: list[Unit] = Field(min_length=1)
    continuity: dict[str, dict[str, float]] = Field(
        default_factory=dict,
        description="ω_c[previous][next] within a layer (missing: 1); 'rest' = nothing before.",
    )
    alpha: float = Field(0.3, ge=0, le=1, description="Eq. 2's rank mix the intensities used.")
    rbf_radius: float = Field(0.5, gt=0, le=10, description="Eq. 5's r.")
    steady_time: float = Field(0.5, gt=0, lt=1, description="φ_time outside L_d and L_w.")
    rest_score: float = Field(
        0.05, ge=0, le=1, description="A layer stays at rest unless a unit scores above this."
    )
    step_s: float = Field(0.02, gt=0, le=0.5, description="Planner time step (s).")
    sources: list[str] = Field(default_factory=list)
    notes: str = ""

    @model_validator(mode="after")
    def _unique(self) -> Library:
        seen: set[str] = set()
        for u in self.units:
            if u.behaviour in seen:
                raise ValueError(f"behaviour {u.behaviour!r} appears twice")
            seen.add(u.behaviour)
        for prev, row in self.continuity.items():
            for name in [prev, *row]:
                if name != "rest" and name not in seen:
                    raise ValueError(f"continuity names unknown behaviour {name!r}")
        return self

    def unit(self, name: str) -> Unit:
        for u in self.units:
            if u.behaviour == name:
                return u
        raise BehaviourError(f"no behaviour {name!r} in the library")

    def layer(self, name: str) -> list[Unit]:
        return [u for u in self.units if u.layer == name]

    def with_motions(self, motions: Library) -> tuple[Library, list[str]]:
        """Fitted statistics with the channels, curves and triggers of same-named units of
        ``motions``; returns the merged library and the behaviours that found no motion."""
        units, missing = [], []
        for u in self.units:
            if u.has_motion:
                units.append(u)
                continue
            try:
                m = motions.unit(u.behaviour)
            except BehaviourError:
                missing.append(u.behaviour)
                units.append(u)
                continue
            units.append(
                u.model_copy(
                    update={
                        k: getattr(m, k)
                        for k in (
                            "channels",
                            "pose_by_emotion",
                            "curve",
                            "triggers",
                            "wait_cv",
                            "speaking_wait_factor",
                            "mirror",
                            "bml",
                        )
                    }
                )
            )
        return self.model_copy(update={"units": units}), missing


def load_library(path: Path | str) -> Library:
    """Read a library (JSON or YAML); errors name the file and the unit at fault."""
    path = Path(path)
    if not path.is_file():
        raise BehaviourError(f"{path}: no such behaviour library")
    text = read_text(path, error=BehaviourError)
    try:
        data = read_data(text, json_too=path.suffix.lower() == ".json")
    except ValueError as exc:  # read_data's own words (a refused alias bomb, a line)
        raise BehaviourError(f"{path}: not readable as JSON or YAML ({exc})") from None
    if not isinstance(data, dict):
        raise BehaviourError(f"{path}: a library is a mapping with 'units'")
    try:
        return Library.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        if first["loc"][:1] == ("units",) and len(first["loc"]) > 1:
            idx = first["loc"][1]
            units = data.get("units") or []
            if isinstance(idx, int) and idx < len(units) and isinstance(units[idx], dict):
                where += f" (behaviour {units[idx].get('behaviour')!r})"
        raise BehaviourError(f"{path}: {where}: {pydantic_message(first)}") from None


_DEFAULT: Library | None = None


def default_library() -> Library:
    """The shipped library for facelab's heads (``stimuli/data/behaviour_default.yaml``)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = load_library(default_library_path())
    return _DEFAULT


def default_library_path() -> Path:
    return package_file("facelab.stimuli", "data", "behaviour_default.yaml")
