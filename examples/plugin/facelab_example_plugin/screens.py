"""``confidence``: after each trial's responses, "how sure are you?" with three buttons.

A template for a new screen kind: a ``ButtonScreen`` subclass declares its name, where it goes
in a trial, its protocol options, its question and buttons, and how a simulated participant
answers. The lab window, the browser (facelab's generic buttons plugin), simulated sessions,
the integrity check and the analysis (``screen_confidence.csv``) take it from there. The
package's ``pyproject.toml`` names the class under the entry-point group ``facelab.screens``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from facelab.experiment.screen_kinds import ButtonScreen

QUESTION = {"ja": "どのくらい確信がありますか？", "en": "How sure are you?"}
LABELS = {
    "ja": ("当て推量", "まあ確か", "確か"),
    "en": ("guessing", "fairly sure", "sure"),
}


class ConfidenceOptions(BaseModel):
    """The protocol's options of the confidence screen."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    question: dict[str, str] | None = Field(None, description="the question, by language")
    p_sure: float = Field(0.5, ge=0, le=1, description="a simulated participant's chance of 3")


class ConfidenceScreen(ButtonScreen):
    kind: ClassVar[str] = "confidence"
    placement: ClassVar[str] = "after_responses"
    Options: ClassVar[type[BaseModel]] = ConfidenceOptions

    def question(self, lang: str) -> str:
        given = self.options.question if self.options is not None else None
        return (given or QUESTION).get(lang) or QUESTION["en"]

    def choices(self, lang: str) -> list[tuple[Any, str]]:
        labels = LABELS.get(lang, LABELS["en"])
        return [(k + 1, label) for k, label in enumerate(labels)]

    def simulate(self, rng: np.random.Generator) -> Any:
        p_sure = self.options.p_sure if self.options is not None else 0.5
        rest = (1.0 - p_sure) / 2
        return int(rng.choice([1, 2, 3], p=[rest, rest, p_sure]))
