"""A SYNTHETIC annotation table, planned from a behaviour library (not from people).

For each of the seven emotions the planner runs ``seconds`` of behaviour at full intensity of
that emotion (neutral: the neutral character), with an utterance-like accent every
``accent_every_s`` so that gestures occur, and every event becomes an annotation row
``emotion, layer, behaviour, start_s, end_s, take``. Fitting the table
(``facelab behaviour fit``) is a round trip: the fitted durations come back close to the
library's (eq. 5 at a pure emotion weights that emotion's value by 1 and the others by
exp(−1/r²)), and units that never fire in an emotion get intensity 0 there.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from facelab.emotions import EMOTIONS
from facelab.stimuli.behaviour.library import Library
from facelab.stimuli.behaviour.plan import EmotionTimeline, SpeechCues, plan_behaviour

__all__ = ["synthetic_annotations"]


def synthetic_annotations(
    *, library: Library, seconds: float = 120.0, seed: int = 1, accent_every_s: float = 0.9
) -> pd.DataFrame:
    """Rows ``emotion, layer, behaviour, start_s, end_s, take`` (take = the emotion)."""
    cues = SpeechCues(
        accents=tuple(np.arange(0.6, seconds - 0.5, accent_every_s)), speaking=((0.0, seconds),)
    )
    rows = []
    for k, emotion in enumerate(EMOTIONS):
        state = EmotionTimeline.constant({emotion: 1.0})
        plan = plan_behaviour(
            library, emotion=state, duration_s=seconds, seed=seed * 100 + k, cues=cues
        )
        rows += [
            (emotion, e.layer, e.unit, round(e.start_s, 3), round(e.end_s, 3), emotion)
            for e in plan.events
        ]
    return pd.DataFrame(rows, columns=["emotion", "layer", "behaviour", "start_s", "end_s", "take"])
