"""The emotion space of seed 003 (EMBOS) and the behaviour settings a condition can name.

Pure data, shared by the protocol model (validation) and the behaviour layer in
``facelab.stimuli``.
"""

from __future__ import annotations

__all__ = ["BEHAVIOUR_MODES", "EMOTIONS", "check_emotion"]

#: The seven emotions of the seed's emotion space, in its order (the vector I of eq. 2).
EMOTIONS: tuple[str, ...] = ("anger", "fear", "joy", "sadness", "disgust", "surprise", "neutral")

#: Condition-level behaviour settings (besides a path to a custom library):
#: ``none`` - no behaviour layer; ``gestures_only`` - the seed's comparison condition:
#: gestures (and blinks) follow the emotion, postures and mannerisms stay neutral;
#: ``composite`` - every layer follows the emotion.
BEHAVIOUR_MODES: tuple[str, ...] = ("none", "gestures_only", "composite")


def check_emotion(values: dict[str, float]) -> dict[str, float]:
    """Raise ValueError unless every key is an emotion and every value lies in [0, 1]."""
    for name, v in values.items():
        if name not in EMOTIONS:
            raise ValueError(f"unknown emotion {name!r}; use {', '.join(EMOTIONS)}")
        if not 0 <= float(v) <= 1:
            raise ValueError(f"emotion {name}={v}: intensities lie in [0, 1]")
    if not values:
        raise ValueError("an emotion needs at least one name: value")
    return values
