"""Screen kinds from outside facelab: the bases a package subclasses, and the loading of the
installed ones (entry-point group ``facelab.screens``).

A protocol asks for an added screen in every trial with ``presentation.added_screens: [{kind:
NAME, options: {...}}]``. The kind (an :class:`AddedScreen` subclass) declares everything
else, so adding one touches only its own package:

* where it goes in a trial (``placement``: ``after_responses`` - after the trial's last
  response screen - or ``after_clip``), its protocol options (``Options``, a pydantic model:
  unknown keys are errors reported with the protocol's line), the item its answers are logged
  under (``item``);
* how it is shown: in the lab window (:meth:`AddedScreen.lab`, drawing with PsychoPy and
  waiting with the window's ``show``), in the browser (``plugin_js``, its own jsPsych plugin,
  given :meth:`AddedScreen.browser_params`), by a simulated participant
  (:meth:`AddedScreen.simulate`); which posted values it accepts (``check_value``);
* its log row: ``screen`` = the kind, ``item``, ``response`` = the answer's value; the
  integrity check expects one such row per trial, and ``facelab analyze`` tabulates the
  answers with the kind's :meth:`AddedScreen.summarise` (``screen_<kind>.csv``; by default per
  condition the counts per value, and the mean when the values are numbers).

:class:`ButtonScreen` is a kind of buttons with all of that defined: a question and choices
are enough (numbered buttons in the lab, facelab's generic buttons plugin in the browser).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict

from facelab.analysis.tasks import answer_counts
from facelab.experiment.timeline import (
    SCREEN_KINDS,
    AnswerError,
    BrowserContext,
    ResponseScreen,
    screen_kind,
)
from facelab.plugins import SCREEN_PLACEMENTS
from facelab.sessionlog import SessionContext

__all__ = [
    "PLACEMENTS",
    "AddedAnswer",
    "AddedScreen",
    "ButtonAnswer",
    "ButtonScreen",
    "NoOptions",
    "load_screen_plugins",
]

PLACEMENTS = SCREEN_PLACEMENTS


class NoOptions(BaseModel):
    """A kind without protocol options (any key is an error)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass(frozen=True)
class AddedAnswer:
    """One answer to an added screen: the value logged as the row's ``response``."""

    value: Any
    rt_s: float
    timestamp: str


#: the answers of button kinds (the same record)
ButtonAnswer = AddedAnswer


@dataclass(frozen=True)
class AddedScreen(ResponseScreen):
    """A screen a package adds to every trial (see the module docstring).

    Subclasses set ``kind`` (and optionally ``item``, ``placement``, ``Options``) and define
    how a simulated participant answers (:meth:`simulate`), how the lab window shows it
    (:meth:`lab`: draw with the window's PsychoPy objects and wait with
    :meth:`facelab.experiment.window.Window.show`) and how the browser shows it (``plugin_js``,
    a jsPsych plugin file setting ``FacelabPlugins[kind]``, given :meth:`browser_params`). They
    may check a posted value (:meth:`check_value`) and tabulate the answers
    (:meth:`summarise`). :class:`ButtonScreen` defines all of it for a row of buttons."""

    kind: ClassVar[str] = "added"
    item: ClassVar[str] = ""  # default: the kind
    placement: ClassVar[str] = "after_responses"
    Options: ClassVar[type[BaseModel]] = NoOptions
    options: Any = None  # an Options instance (from the protocol's added_screens entry)

    # ---------------------------------------------------------------- to define
    def simulate(self, rng: np.random.Generator) -> Any:
        """A simulated participant's answer (the value logged)."""
        raise NotImplementedError(f"screen kind {self.kind!r} does not define simulate()")

    def lab(self, window: Any) -> tuple[Any, float]:
        """Show the screen in the lab window; returns (value, response time in s). A scripted
        participant answers :meth:`simulate`'s value (``window.scripted_value(self)``)."""
        raise NotImplementedError(f"screen kind {self.kind!r} cannot be shown in the lab "
                                  "window (it does not define lab())")  # fmt: skip

    def browser_params(self, lang: str) -> dict[str, Any]:
        """The parameters of the kind's jsPsych plugin besides kind, trial_index, item and
        practice."""
        return {}

    def check_value(self, value: Any) -> Any:
        """The value a browser posted, as logged; :class:`AnswerError` when it does not fit."""
        if value is None or isinstance(value, (dict, list)):
            raise AnswerError(f"value: expected a number or a word, got {value!r}")
        return value

    @classmethod
    def summarise(cls, rows: pd.DataFrame) -> pd.DataFrame:
        """The analysis table of the answers (``screen_<kind>.csv``) from their log rows (one
        per trial: condition, stimulus, response, ...): by default per condition the count
        and share of each answer, and mean, sd and n when the answers are numbers."""
        return answer_counts(rows)

    # ---------------------------------------------------------------- provided
    @classmethod
    def item_id(cls) -> str:
        return cls.item or cls.kind

    def response_keys(self) -> tuple[tuple[int, str], ...]:
        if self.practice or self.trial is None:
            return ()
        return ((self.trial.trial_index, self.item_id()),)

    def browser(self, ctx: BrowserContext) -> dict[str, Any]:
        return {
            "kind": self.kind, "trial_index": self.trial_index, "item": self.item_id(),
            "practice": self.practice, **self.browser_params(ctx.lang),
        }  # fmt: skip

    def answer(
        self, item: str, posted: Mapping[str, Any], *, rt_s: float, timestamp: str
    ) -> AddedAnswer:
        return AddedAnswer(self.check_value(posted.get("value")), rt_s, timestamp)

    def posted(self, answer: AddedAnswer) -> dict[str, Any]:
        return {"value": answer.value}

    def row(
        self, item: str, answer: AddedAnswer, *, context: SessionContext, playback: Any
    ) -> dict[str, Any]:
        return self._row(context=context, playback=playback, item=item, rt_s=answer.rt_s,
                         timestamp=answer.timestamp, response=str(answer.value))  # fmt: skip

    def present(self, presenter: Any) -> list[AddedAnswer]:
        """The lab window and simulated participants answer any added kind
        (``added_screen``: the window through :meth:`lab`, a simulation through
        :meth:`simulate`)."""
        return presenter.added_screen(self)


@dataclass(frozen=True)
class ButtonScreen(AddedScreen):
    """A screen of buttons after each trial. Subclasses set ``kind`` (and optionally
    ``item``, ``placement``, ``Options``) and define :meth:`question` and :meth:`choices`;
    :meth:`simulate` may model a participant. The lab window draws numbered buttons, the
    browser facelab's generic buttons plugin (no JavaScript to write)."""

    kind: ClassVar[str] = "buttons"

    # ---------------------------------------------------------------- to define
    def question(self, lang: str) -> str:
        raise NotImplementedError

    def choices(self, lang: str) -> list[tuple[Any, str]]:
        """(value, label) per button, left to right."""
        raise NotImplementedError

    def simulate(self, rng: np.random.Generator) -> Any:
        """A simulated participant's answer (default: a button at random)."""
        values = [v for v, _ in self.choices("en")]
        return values[int(rng.integers(len(values)))]

    # ---------------------------------------------------------------- provided
    def lab(self, window: Any) -> tuple[Any, float]:
        return window.buttons(self)

    def browser_params(self, lang: str) -> dict[str, Any]:
        return {
            "widget": "buttons", "question": self.question(lang),
            "choices": [{"value": v, "label": label} for v, label in self.choices(lang)],
        }  # fmt: skip

    def check_value(self, value: Any) -> Any:
        values = [v for v, _ in self.choices("en")]
        if isinstance(value, bool) or value not in values:
            raise AnswerError(f"value: expected one of {', '.join(map(str, values))}, "
                              f"got {value!r}")  # fmt: skip
        # the choice's own value (a browser's JSON may turn 2 into 2.0)
        return values[values.index(value)]


def load_screen_plugins() -> list[str]:
    """Register the installed screen kinds (entry-point group ``facelab.screens``: a
    :class:`AddedScreen` subclass whose ``kind`` is the entry point's name); problems are
    recorded in the entries (``facelab plugins``) and returned."""
    from facelab.plugins import GROUPS, plugin_entries

    problems = []
    for entry in plugin_entries(GROUPS["screens"]):
        if entry.problem is not None:
            problems.append(entry.problem)
            continue
        # the class, name, placement and plugin file are checked when the entry loads
        # (facelab.plugins); here: a name facelab's own kinds already take
        obj = entry.obj
        where = f"plugin {entry.name!r} from package {entry.package!r} ({entry.value})"
        if SCREEN_KINDS.get(obj.kind, obj) is not obj:
            entry.problem = f"{where}: a screen kind named {obj.kind!r} exists already"
        else:
            screen_kind(obj)
        if entry.problem is not None:
            problems.append(entry.problem)
    return problems
