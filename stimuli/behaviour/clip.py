"""The behaviour layer of one clip: which library, which layers, which emotion, which seed.

A condition's ``behaviour`` setting (:data:`facelab.emotions.BEHAVIOUR_MODES` or a library
file) and the emotion (the condition's, else the stimulus's, else neutral) decide the plan;
:func:`clip_seed` derives the planner's seed from the protocol's ``behaviour_seed`` and the
stimulus, so every condition showing a stimulus draws the same random numbers per layer
(yoked randomness: the same blink times wherever the blink layer is planned alike).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facelab.emotions import BEHAVIOUR_MODES
from facelab.stimuli.avatar.rig import HeadPose
from facelab.stimuli.behaviour.library import LAYERS, Library, default_library, load_library
from facelab.stimuli.behaviour.plan import EmotionTimeline, Plan, SpeechCues, plan_behaviour
from facelab.stimuli.behaviour.realise import apply_to_weights, avatar_traits, realise

__all__ = ["ClipBehaviour", "behaviour_for_clip", "clip_seed", "layers_for"]


def layers_for(mode: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(layers planned, layers kept neutral) for a behaviour mode."""
    if mode == "none":
        return (), ()
    if mode == "gestures_only":  # the seed's comparison: postures and mannerisms unchanged
        return tuple(layer for layer in LAYERS if layer not in ("posture", "mannerism")), ()
    if mode == "neutral_composite":  # same kinds of motion, only gestures and blinks emotional
        return LAYERS, ("posture", "mannerism")
    return LAYERS, ()


def clip_seed(behaviour_seed: int, stimulus_set: str, stimulus: str) -> int:
    """A 31-bit seed from the protocol's seed and the stimulus (not the condition)."""
    h = hashlib.sha256(f"{behaviour_seed}/{stimulus_set}/{stimulus}".encode()).digest()
    return int.from_bytes(h[:4], "big") & 0x7FFFFFFF


@dataclass
class ClipBehaviour:
    """A clip's plan and what realising it on the avatar did."""

    mode: str
    library_name: str
    library: Library
    plan: Plan
    weights: np.ndarray  # (n_frames, K) speech + behaviour, clamped
    poses: list[HeadPose | None]
    report: dict

    def log(self) -> dict:
        """The event log written beside the clip (``<clip>.behaviour.json``)."""
        return {
            "mode": self.mode,
            "library": self.library_name,
            **self.plan.to_json(),
            "realisation": self.report,
        }

    def summary(self) -> dict:
        return {
            "mode": self.mode,
            "library": self.library_name,
            "seed": self.plan.seed,
            "emotion": self.plan.emotion,
            "counts": self.plan.counts(),
            "clamped_frames": self.report.get("clamped_frames", {}),
            "dropped": self.report.get("dropped", {}),
        }


def emotion_timeline(emotion: dict[str, float] | list[dict[str, float]] | None) -> EmotionTimeline:
    """A protocol's emotion - a vector, a list of ``{time_s, <emotion>: v}`` keys, or None
    (neutral) - as the planner's timeline."""
    if emotion is None:
        return EmotionTimeline.constant({"neutral": 1.0})
    if isinstance(emotion, list):
        return EmotionTimeline.from_keys(
            (float(k["time_s"]), {n: float(v) for n, v in k.items() if n != "time_s"})
            for k in emotion
        )
    return EmotionTimeline.constant(emotion)


def behaviour_for_clip(
    *,
    setting: str,
    emotion: dict[str, float] | list[dict[str, float]] | None,
    base_dir: Path,
    seed: int,
    speech,
    pad_s: float,
    fps: int,
    n_frames: int,
    weights: np.ndarray,
    avatar,
) -> ClipBehaviour | None:
    """Plan and realise the behaviour of one clip (None for ``none``).

    ``weights`` (n_frames, K) are the speech animation's frame weights in the avatar's
    target order; ``speech`` the unpadded :class:`~facelab.stimuli.speech.audio.Speech`."""
    if setting == "none":
        return None
    if setting in BEHAVIOUR_MODES:
        library, name, mode = default_library(), "default", setting
    else:
        library, name, mode = load_library(base_dir / setting), setting, "composite"
    layers, neutral = layers_for(mode)
    plan = plan_behaviour(
        library,
        emotion=emotion_timeline(emotion),
        duration_s=n_frames / fps,
        seed=seed,
        cues=SpeechCues.from_speech(speech, offset_s=pad_s),
        layers=layers,
        neutral_layers=neutral,
    )
    frames = realise(plan, library, fps=fps, n_frames=n_frames)
    out, poses, report = apply_to_weights(frames, weights, **avatar_traits(avatar))
    return ClipBehaviour(mode, name, library, plan, out, poses, report)
