"""``effort``: right after each clip, "how hard was the speech to follow?" on a 1-7 row of
circles - a template for a screen kind that draws itself.

Unlike a ``ButtonScreen`` (question and choices, facelab draws the rest) this kind defines
every part of an ``AddedScreen``: its lab drawing (PsychoPy circles, keys 1-7 or a click,
:meth:`EffortScreen.lab`), its own jsPsych plugin (``effort.js``, shipped as package data),
which posted values it accepts, a simulated participant, and its own analysis table
(``screen_effort.csv``: median and quartiles per condition). The package's ``pyproject.toml``
names the class under the entry-point group ``facelab.screens``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field

from facelab.experiment.screen_kinds import AddedScreen
from facelab.experiment.timeline import AnswerError

POINTS = 7
TEXT = {
    "en": ("How hard was the speech to follow?", "very easy", "very hard"),
    "ja": ("話を聞き取るのはどのくらい難しかったですか？", "とても易しい", "とても難しい"),
}


class EffortOptions(BaseModel):
    """The protocol's options of the effort screen."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    mean: float = Field(3.0, ge=1, le=POINTS, description="a simulated participant's mean")


class EffortScreen(AddedScreen):
    kind: ClassVar[str] = "effort"
    placement: ClassVar[str] = "after_clip"
    Options: ClassVar[type[BaseModel]] = EffortOptions
    plugin_js: ClassVar[Path | None] = Path(__file__).with_name("effort.js")

    def _text(self, lang: str) -> tuple[str, str, str]:
        return TEXT.get(lang, TEXT["en"])

    def simulate(self, rng: np.random.Generator) -> Any:
        mean = self.options.mean if self.options is not None else 3.0
        return int(np.clip(round(rng.normal(mean, 1.2)), 1, POINTS))

    def check_value(self, value: Any) -> Any:
        if isinstance(value, bool) or value not in range(1, POINTS + 1):
            raise AnswerError(f"value: expected a whole number 1 to {POINTS}, got {value!r}")
        return int(value)

    def browser_params(self, lang: str) -> dict[str, Any]:
        question, easy, hard = self._text(lang)
        return {"question": question, "anchors": [easy, hard], "points": POINTS}

    def lab(self, window: Any) -> tuple[Any, float]:
        """Seven numbered circles between the anchors; keys 1-7 or a click."""
        question, easy, hard = self._text(window.lang)
        w, h = window.size
        step = 0.09 * w
        xs = [(k - (POINTS - 1) / 2) * step for k in range(POINTS)]
        circles = [window.visual.Circle(window.win, radius=0.035 * w, pos=(x, 0),
                                        lineColor="white", lineWidth=2,
                                        fillColor=(-0.45, -0.45, -0.45)) for x in xs]  # fmt: skip
        numbers = [window.text_stim(str(k + 1), y=0, height=0.04 * h, width=0.06 * w)
                   for k in range(POINTS)]  # fmt: skip
        for stim, x in zip(numbers, xs, strict=True):
            stim.pos = (x, 0)
        anchors = [window.text_stim(easy, y=-0.1 * h, height=0.028 * h, width=0.2 * w),
                   window.text_stim(hard, y=-0.1 * h, height=0.028 * h, width=0.2 * w)]  # fmt: skip
        anchors[0].pos, anchors[1].pos = (xs[0], -0.1 * h), (xs[-1], -0.1 * h)
        value = window.scripted_value(self)
        scripted = None if value is None else (str(value), value, self.trial_index, self.item_id())
        keys = {str(k): k for k in range(1, POINTS + 1)} | {
            f"num_{k}": k for k in range(1, POINTS + 1)
        }
        return window.show(
            stims=[window.text_stim(question, y=0.2 * h), *circles, *numbers, *anchors],
            keys=keys, clickable=[(c, k + 1) for k, c in enumerate(circles)],
            shot=None if self.practice else "effort_screen", scripted=scripted,
        )  # fmt: skip

    @classmethod
    def summarise(cls, rows: pd.DataFrame) -> pd.DataFrame:
        """Per condition: n, median and quartiles, mean, and the share rated hard (5-7)."""
        value = pd.to_numeric(rows["response"])
        grouped = rows.assign(value=value).groupby("condition", observed=True)["value"]
        return grouped.agg(
            n="count",
            median="median",
            q1=lambda v: v.quantile(0.25),
            q3=lambda v: v.quantile(0.75),
            mean="mean",
            share_hard=lambda v: float((v >= 5).mean()),
        ).reset_index()
