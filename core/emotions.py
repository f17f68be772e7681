"""The emotion space of seed 003 (EMBOS) and the behaviour settings a condition can name.

Pure data, shared by the protocol model (validation) and the behaviour layer in
``facelab.stimuli``.
"""

from __future__ import annotations

__all__ = ["BEHAVIOUR_MODES", "EMOTIONS", "check_emotion", "check_emotion_keys", "emotion_of"]

#: The seven emotions of the seed's emotion space, in its order (the vector I of eq. 2).
EMOTIONS: tuple[str, ...] = ("anger", "fear", "joy", "sadness", "disgust", "surprise", "neutral")

#: Condition-level behaviour settings (besides a path to a custom library):
#: ``none`` - no behaviour layer; ``gestures_only`` - the seed's comparison condition
#: ("姿勢、しぐさは変化せずにジェスチャの変化のみ"): gestures and blinks follow the emotion,
#: postures and mannerisms do not change (none is planned; the head keeps its rest posture);
#: ``neutral_composite`` - a control with the same kinds of motion as ``composite``: every
#: layer is planned, postures and mannerisms for a neutral character, gestures and blinks
#: from the emotion; ``composite`` - every layer follows the emotion.
BEHAVIOUR_MODES: tuple[str, ...] = ("none", "gestures_only", "neutral_composite", "composite")


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


def check_emotion_keys(keys: list[dict[str, float]]) -> list[dict[str, float]]:
    """Raise ValueError unless ``keys`` is an emotion timeline: a non-empty list of
    ``{time_s: s, <emotion>: value, …}`` with times >= 0 strictly increasing, each key's
    emotions valid (:func:`check_emotion`)."""
    if not keys:
        raise ValueError("an emotion timeline needs at least one key {time_s: s, emotion: v}")
    last = -1.0
    for i, key in enumerate(keys):
        if "time_s" not in key:
            raise ValueError(f"emotion timeline key {i + 1}: no time_s (seconds in the clip)")
        t = float(key["time_s"])
        if t < 0 or t <= last:
            raise ValueError(
                f"emotion timeline key {i + 1}: time_s {t:g} must be >= 0 and after the "
                f"previous key's ({last:g})"
            )
        last = t
        check_emotion({k: v for k, v in key.items() if k != "time_s"})
    return keys


Emotion = dict[str, float] | list[dict[str, float]]


def emotion_of(value: Emotion) -> Emotion:
    """Validate a protocol emotion: one vector (``{joy: 0.8}``) or a timeline
    (``[{time_s: 0, joy: 0.8}, {time_s: 4, sadness: 0.6}]``)."""
    return check_emotion_keys(value) if isinstance(value, list) else check_emotion(value)
